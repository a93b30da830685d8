"""The learned edge scorer at inference: which candidates a model with an edge head scores,
and its match probability for each.

A GCN with an edge head (``GCNConfig.edge_features > 0``, the shipped models) scores the
candidate edges of :func:`.candidates.candidate_edges` built with ``k = GCNConfig.edge_k``
from its node embeddings and the candidates' pose-free features
(:meth:`gcn_match_ros.learn.model.GCN.score_edges`). Training it is
:func:`gcn_match_ros.learn.objective.edge_training_loss`.
"""
from __future__ import annotations

import numpy as np
import torch

from ..threads import one_torch_thread
from .candidates import EdgeConfig, EdgeSet

__all__ = ["has_edge_head", "edge_config_of", "edge_probabilities"]


def has_edge_head(model: torch.nn.Module) -> bool:
    """True when ``model`` scores candidate edges itself (else scores are EEᵀ)."""
    return getattr(model, "edge_head", None) is not None


def edge_config_of(model: torch.nn.Module) -> EdgeConfig:
    """The candidate edges a model with an edge head was trained on."""
    return EdgeConfig(k=int(model.config.edge_k))


def edge_probabilities(model: torch.nn.Module, embeddings: torch.Tensor, edges: EdgeSet) -> np.ndarray:
    """sigmoid of the head's logit for every candidate edge (no gradients: inference), on one
    torch thread, so that the bits do not depend on how many threads the caller has at the moment
    (:func:`gcn_match_ros.threads.one_torch_thread`); on this project's 2-core machine the head
    is also faster so (4 x 500 window: 15.5 against 23.5 ms on two threads; 10 x 1000: 104-130
    against 260-346 ms).

    Shapes: embeddings (N, d) on the model's device, edges with M candidates -> (M,) float32.
    """
    with one_torch_thread(), torch.no_grad():
        logits = model.score_edges(embeddings, torch.from_numpy(edges.rows), torch.from_numpy(edges.cols),
                                   torch.from_numpy(edges.features))
    return torch.sigmoid(logits).cpu().numpy()
