"""Glue between the GCN's optional edge head, its candidate edges and the training loss.

``edge_inputs`` builds (and caches per problem name) the candidate edges and their
pose-free features; ``edge_training_loss`` is the extra term :func:`train.train_step`
adds when ``TrainConfig.edge_weight > 0``: reconstruction of the candidate adjacency plus
the epipolar term from the true poses (:func:`losses.edge_loss`). No match labels.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch

from .edge_features import EdgeConfig, EdgeSet, candidate_edges
from .losses import edge_loss, pixel_epipolar_residuals
from .problem import Problem

__all__ = ["edge_inputs", "edge_training_loss", "edge_config_of"]

_CACHE: "OrderedDict[tuple, tuple]" = OrderedDict()
_CACHE_SIZE = 256


def edge_config_of(net) -> EdgeConfig:
    return EdgeConfig(k=int(net.config.edge_k))


def edge_inputs(problem: Problem, config: EdgeConfig, with_residuals: bool = False, cache: bool = False):
    """(EdgeSet, true-pose pixel residuals or None). Cached by problem name when ``cache``."""
    key = (problem.name, problem.n_keypoints, config, with_residuals)
    if cache and problem.name and key in _CACHE:
        return _CACHE[key]
    es = candidate_edges(problem, config)
    res = None
    if with_residuals:
        res = np.full(es.rows.shape[0], np.inf)
        view = problem.view_index
        va, vb = view[es.rows], view[es.cols]
        for a in range(problem.n_views):
            for b in range(a + 1, problem.n_views):
                m = (va == a) & (vb == b)
                if m.any():
                    res[m] = pixel_epipolar_residuals(
                        problem.keypoints[es.rows[m]].astype(np.float64),
                        problem.keypoints[es.cols[m]].astype(np.float64),
                        problem.K[a], problem.R[a], problem.t[a], problem.K[b], problem.R[b], problem.t[b])
    out = (es, res)
    if cache and problem.name:
        _CACHE[key] = out
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return out


def edge_training_loss(net, E: torch.Tensor, problem: Problem) -> torch.Tensor:
    """Edge-head loss of one posed problem (``net``: a GCN with ``edge_head``)."""
    es, res = edge_inputs(problem, edge_config_of(net), with_residuals=True, cache=True)
    if es.rows.shape[0] == 0:
        return E.sum() * 0.0
    logits = net.score_edges(E, torch.from_numpy(es.rows), torch.from_numpy(es.cols),
                             torch.from_numpy(es.features))
    return edge_loss(logits, torch.from_numpy(np.minimum(res, 1e3)))
