"""Training of the GCN: the resumable, optionally distributed training loop.

:func:`train`: the loop — Adam with exponential decay, validation, atomic checkpoints
``checkpoint.pt`` / ``best.pt``, ``history.json``, ``resume``, and distributed data
parallel training (:mod:`.ddp`). Its data come from :mod:`.sources`, its loss from
:mod:`.objective`, its settings from :class:`.config.TrainConfig`.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
import warnings
from itertools import islice
from pathlib import Path
from typing import Any, Dict, List, Optional, Union

import numpy as np
import torch

from .. import plots
from ..node_features import feature_dim
from ..problem import Problem, atomic_write
from . import ddp
from .checkpoint import load_checkpoint, save_checkpoint
from .config import TrainConfig
from .model import GCN, GCNConfig
from .objective import Sample, TrainingObjective, evaluate, make_batch, make_sample, train_step
from .sources import DataSource, ShardedSource

__all__ = ["train"]


def _rng_state() -> Dict[str, Any]:
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(),
            "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), int(pos), int(has_gauss), float(cached)]}


def _set_rng_state(state: Dict[str, Any]) -> None:
    if "torch" in state:
        torch.set_rng_state(state["torch"])
    if "numpy" in state:
        kind, keys, pos, has_gauss, cached = state["numpy"]
        np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))


def _write_json(path: Path, obj: Any) -> None:
    text = json.dumps(obj, indent=1, allow_nan=True)
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def _check_feature_dim(sample: Sample, model_config: GCNConfig, config: TrainConfig) -> None:
    f = sample.features.shape[1]
    if f != model_config.in_dim:
        d = sample.problem.descriptors.shape[1]
        raise ValueError(f"node features have F={f} columns (descriptor D={d}, {config.features}) but "
                         f"model_config.in_dim={model_config.in_dim}; use in_dim=feature_dim({d}, features)"
                         f" = {feature_dim(d, config.features)}")


def train(model_config: GCNConfig, train_source: DataSource, val_source: Optional[DataSource] = None,
          train_config: TrainConfig = TrainConfig(), out_dir: Union[str, Path] = "runs/gcn",
          resume: bool = False, init: Optional[Union[str, Path]] = None,
          distributed: bool = False) -> Dict[str, Any]:
    """Train a :class:`model.GCN`, writing checkpoints and the history to ``out_dir``.

    Files (all written atomically):
        ``checkpoint.pt``: latest model + optimizer + scheduler + step + RNG states +
        best-so-far (every ``checkpoint_every`` steps and at the end);
        ``best.pt``: the model with the lowest validation loss (without a validation
        source: the lowest mean training loss over a checkpoint interval);
        ``history.json``: ``{"train": [...], "val": [...], "best": {...}}`` entries with ``step``.
        ``curves.png``: training / validation curves (:func:`plots.plot_history`, at the end,
        when ``train_config.plot``).
    Both ``.pt`` files load with :func:`model.load_checkpoint` and carry the graph and
    feature settings (``train_config.graph`` / ``.features``) inference must reuse.

    Distributed (``distributed=True``, after ``torch.distributed.init_process_group``, e.g.
    under ``torchrun``; see :mod:`train_ddp`): every rank calls ``train`` with the same
    arguments; the model is wrapped in ``DistributedDataParallel`` (gradients averaged over
    ranks), rank r trains on its :class:`ShardedSource` share of ``train_source`` (the
    effective batch is ``batch_size × world_size``), logged training losses are averaged
    over all ranks, and only rank 0 validates and writes files and the progress bar.

    Args:
        model_config: architecture; ``in_dim`` must equal the feature dimension.
        train_source: a :class:`DataSource` (should be endless).
        val_source: a :class:`DataSource`; its first ``val_size`` problems are the validation set.
        train_config: :class:`TrainConfig`.
        out_dir: output folder (created).
        resume: continue from ``out_dir/checkpoint.pt`` if it exists (same step count,
            optimizer, scheduler and RNG state; the data stream restarts at the
            position the run had reached).
        init: start from this checkpoint's weights (ignored when resuming from a checkpoint);
            its architecture must equal ``model_config``.
        distributed: train data-parallel over the initialised default process group.

    Returns:
        the history dict (also in ``history.json``).
    """
    from tqdm.auto import tqdm

    cfg = train_config
    rank, world = ddp.rank_and_world(distributed)
    main = rank == 0
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path, best_path, hist_path = out / "checkpoint.pt", out / "best.pt", out / "history.json"

    torch.manual_seed(cfg.seed)
    model = GCN(model_config)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=cfg.lr_gamma ** (1.0 / cfg.lr_decay_steps))
    step = 0
    history: Dict[str, Any] = {"train": [], "val": [], "best": None}
    best: Optional[Dict[str, Any]] = None

    if resume and ckpt_path.is_file():
        saved, meta = load_checkpoint(ckpt_path)
        if meta["model_config"] != model_config:
            raise ValueError(f"resume: {ckpt_path} was trained with {meta['model_config']}, not {model_config}")
        extra = meta["extra"]
        model.load_state_dict(saved.state_dict())
        optimizer.load_state_dict(extra["optimizer"])
        scheduler.load_state_dict(extra["scheduler"])
        step = int(extra["step"])
        best = extra.get("best")
        _set_rng_state(extra.get("rng", {}))
        if hist_path.is_file():
            history = json.loads(hist_path.read_text())
            history["train"] = [h for h in history.get("train", []) if h["step"] <= step]
            history["val"] = [h for h in history.get("val", []) if h["step"] <= step]
        history["best"] = best
    elif init is not None:
        saved, meta = load_checkpoint(init)
        if meta["model_config"] != model_config:
            raise ValueError(f"init: {init} has architecture {meta['model_config']}, not {model_config}")
        model.load_state_dict(saved.state_dict())

    net: torch.nn.Module = model
    if distributed:
        net = ddp.wrap(TrainingObjective(model, cfg), has_edge_head=getattr(model, "edge_head", None) is not None)

    config_dict = {"model": model_config.to_dict(), "graph": dataclasses.asdict(cfg.graph),
                   "features": cfg.features.to_dict(), "train": cfg.to_dict()}

    def checkpoint(path: Path, with_state: bool) -> None:
        extra = {"step": step, "best": best}
        if with_state:
            extra.update(optimizer=optimizer.state_dict(), scheduler=scheduler.state_dict(), rng=_rng_state())
        save_checkpoint(path, model, config_dict, extra)

    def sample_of(problem: Problem) -> Sample:
        return make_sample(problem, cfg.graph, cfg.features)

    val_samples = ([sample_of(p) for p in islice(val_source(0), cfg.val_size)]
                   if val_source is not None and main else [])
    shard = ShardedSource(train_source, rank, world) if world > 1 else train_source
    train_iter = shard(step * cfg.batch_size)
    model.train()
    interval: Dict[str, List[float]] = {}
    since_ckpt: List[float] = []
    last_val = history["val"][-1]["loss"] if history["val"] else float("nan")
    checked = False
    t0 = time.perf_counter()
    bar = tqdm(total=cfg.steps, initial=step, disable=not (cfg.progress and main), desc="train",
               dynamic_ncols=True)
    try:
        while step < cfg.steps:
            try:
                samples = [sample_of(next(train_iter)) for _ in range(cfg.batch_size)]
            except StopIteration:
                raise ValueError(f"train_source ran out of problems at step {step}; "
                                 f"training sources must be endless (cycle)") from None
            if not checked:
                _check_feature_dim(samples[0], model_config, cfg)
                checked = True
            optimizer.zero_grad(set_to_none=True)
            loss, logs = train_step(net, make_batch(samples), cfg)
            loss.backward()
            if cfg.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            scheduler.step()
            step += 1
            for k, v in logs.items():
                if not math.isnan(v):
                    interval.setdefault(k, []).append(v)
            since_ckpt.append(logs["loss"])
            bar.update(1)
            bar.set_postfix(loss=f"{logs['loss']:.4f}", val=f"{last_val:.4f}")

            last = step == cfg.steps
            if step % cfg.log_every == 0 or last:
                means = {k: float(np.mean(v)) for k, v in interval.items()}
                if world > 1:  # mean over every rank's values (same keys on all ranks: same code)
                    keys = sorted(logs)
                    sums = ddp.all_reduce_sums([x for k in keys for x in (float(np.sum(interval.get(k, []))),
                                                                         float(len(interval.get(k, []))))])
                    means = {k: sums[2 * i] / sums[2 * i + 1] for i, k in enumerate(keys) if sums[2 * i + 1]}
                entry = {"step": step, **means,
                         "lr": scheduler.get_last_lr()[0], "seconds": time.perf_counter() - t0}
                history["train"].append(entry)
                interval = {}
            improved = False
            if val_samples and (step % cfg.val_every == 0 or last):
                val = evaluate(model, val_samples, cfg)
                last_val = val["loss"]
                history["val"].append({"step": step, **val})
                if best is None or val["loss"] < best["loss"]:
                    best, improved = {"step": step, "loss": val["loss"], "source": "val"}, True
            if step % cfg.checkpoint_every == 0 or last:
                if world > 1:
                    total_n = ddp.all_reduce_sums([float(np.sum(since_ckpt)), float(len(since_ckpt))])
                    since_ckpt = [total_n[0] / total_n[1]] if total_n[1] else []
                if not val_samples and since_ckpt and main:
                    mean_train = float(np.mean(since_ckpt))
                    if best is None or mean_train < best["loss"]:
                        best, improved = {"step": step, "loss": mean_train, "source": "train"}, True
                since_ckpt = []
            if improved and main:
                history["best"] = best
                checkpoint(best_path, with_state=False)
            if (step % cfg.checkpoint_every == 0 or last) and main:
                checkpoint(ckpt_path, with_state=True)
                _write_json(hist_path, history)
    finally:
        bar.close()
    if main and cfg.plot and (history["train"] or history["val"]):
        try:
            plots.plot_history([history], out / "curves.png", labels=[out.name])
        except Exception as exc:  # noqa: BLE001 - a failed plot must not fail a finished run
            warnings.warn(f"could not write {out / 'curves.png'}: {type(exc).__name__}: {exc}")
    if world > 1:
        ddp.barrier()  # every rank returns once rank 0's files are written
    return history

