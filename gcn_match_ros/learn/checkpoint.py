"""Checkpoints of the GCN: weights plus the JSON configuration inference needs.

A checkpoint is a ``torch.save`` of plain data — format tag, version, the JSON config
(``model``: :class:`~.model.GCNConfig`, ``graph``: :class:`~gcn_match_ros.graph.GraphConfig`,
``features``: :class:`~gcn_match_ros.node_features.FeatureConfig`, ``solver``: e.g. the
rounding threshold chosen with the model, ``train``), the ``state_dict`` and the training
state — so :func:`load_checkpoint` reads it with ``torch.load(weights_only=True)`` and never
unpickles code. Writes are atomic (temporary file + rename): a crash never leaves half a file.
"""
from __future__ import annotations

import json
import os
from typing import Any, Dict, Optional, Tuple

import torch
from torch import nn

from ..graph import GraphConfig
from ..node_features import FeatureConfig
from ..problem import atomic_write
from .model import GCN, GCNConfig

__all__ = ["CHECKPOINT_FORMAT", "CheckpointError", "save_checkpoint", "load_checkpoint"]

CHECKPOINT_FORMAT = "gcn_match_ros/gcn-checkpoint"
CHECKPOINT_VERSION = 1


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, or does not fit the model code."""


def _unwrap(model: nn.Module) -> nn.Module:
    return model.module if hasattr(model, "module") and isinstance(model.module, nn.Module) else model


def save_checkpoint(path, model: GCN, config_dict: Optional[Dict[str, Any]] = None,
                    extra: Optional[Dict[str, Any]] = None) -> None:
    """Write model weights and configuration atomically (temp file + rename).

    Args:
        path: destination file (``.pt``).
        model: the :class:`GCN` (a DDP wrapper is unwrapped).
        config_dict: JSON-able configuration; keys ``"model"`` (:meth:`GCNConfig.to_dict`,
            filled from the model when missing), ``"graph"`` (GraphConfig fields),
            ``"features"`` (:meth:`FeatureConfig.to_dict`), and anything else
            (e.g. ``"train"``). Inference rebuilds its input from ``graph``/``features``.
        extra: training state loadable with ``weights_only=True``: tensors, numbers,
            strings, lists/tuples/dicts of those (optimizer / scheduler state dicts,
            ``step``, RNG states).

    Raises:
        ValueError: config_dict is not JSON-serialisable.
    """
    net = _unwrap(model)
    config = dict(config_dict or {})
    config.setdefault("model", net.config.to_dict())
    try:
        json.dumps(config)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"save_checkpoint: config_dict is not JSON-serialisable ({exc})") from None
    payload = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": config,
        "state_dict": {k: v.detach().cpu() for k, v in net.state_dict().items()},
        "extra": extra or {},
    }
    atomic_write(path, lambda tmp: torch.save(payload, tmp))


def load_checkpoint(path, map_location: str = "cpu") -> Tuple[GCN, Dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint` (``torch.load(weights_only=True)``).

    Returns:
        ``(model, meta)``: the :class:`GCN` in eval mode, and ``meta`` with keys
        ``config`` (the saved dict), ``model_config`` (:class:`GCNConfig`),
        ``graph_config`` (:class:`graph.GraphConfig`), ``feature_config``
        (:class:`features.FeatureConfig`), ``extra`` (training state) and ``path``.

    Raises:
        CheckpointError: missing or unreadable file, not a gcn_match_ros checkpoint,
            an invalid configuration, or weights that do not fit it.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # corrupt zip, truncated file, refused pickle, ...
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise CheckpointError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {msg[:200]})") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: not a {CHECKPOINT_FORMAT} file")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{path}: checkpoint version {payload.get('version')!r} is not supported "
                              f"(expected {CHECKPOINT_VERSION})")
    config = payload.get("config")
    state = payload.get("state_dict")
    if not isinstance(config, dict) or not isinstance(config.get("model"), dict) or not isinstance(state, dict):
        raise CheckpointError(f"{path}: checkpoint lacks 'config.model' or 'state_dict'")
    try:
        model_config = GCNConfig.from_dict(config["model"])
        graph_config = GraphConfig.from_dict(config.get("graph") or {})
        feature_config = FeatureConfig.from_dict(config.get("features") or {})
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: invalid configuration ({exc})") from None
    model = GCN(model_config)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise CheckpointError(f"{path}: weights do not fit the configured model "
                              f"({' '.join(s.strip() for s in first[:3])[:300]})") from None
    model.eval()
    meta = {"config": config, "model_config": model_config, "graph_config": graph_config,
            "feature_config": feature_config, "extra": payload.get("extra") or {}, "path": path}
    return model, meta

