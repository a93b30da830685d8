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

from ..learn.model import EDGE_CHUNK
from ..threads import alongside, one_torch_thread
from .candidates import EdgeConfig, EdgeSet

__all__ = ["has_edge_head", "edge_config_of", "edge_probabilities", "SPLIT_EDGES"]

#: candidate edges from which the head's work is split over both threads: below two chunks
#: there is nothing to split at a chunk boundary
SPLIT_EDGES = 2 * EDGE_CHUNK


def has_edge_head(model: torch.nn.Module) -> bool:
    """True when ``model`` scores candidate edges itself (else scores are EEᵀ)."""
    return getattr(model, "edge_head", None) is not None


def edge_config_of(model: torch.nn.Module) -> EdgeConfig:
    """The candidate edges a model with an edge head was trained on."""
    return EdgeConfig(k=int(model.config.edge_k))


def edge_probabilities(model: torch.nn.Module, embeddings: torch.Tensor, edges: EdgeSet,
                       parallel: bool = True) -> np.ndarray:
    """sigmoid of the head's logit for every candidate edge (no gradients: inference).

    Each part runs on one torch thread, so that the bits do not depend on how many threads the
    caller has at the moment (:func:`gcn_match_ros.threads.one_torch_thread`); on this project's
    2-core machine the head is also faster so (4 x 500 window: 15.5 against 23.5 ms on two
    threads; 10 x 1000: 104-130 against 260-346 ms). With ``parallel`` and at least
    :data:`SPLIT_EDGES` edges, the second half runs on the process's second thread
    (:func:`gcn_match_ros.threads.alongside`), or back on the caller's when that thread is still
    busy once the first half is done. The halves meet at a multiple of the head's own chunk
    (:data:`gcn_match_ros.learn.model.EDGE_CHUNK`): the same chunks, so the same bits, as one pass.

    On a GPU the head runs in one pass: its kernels queue on one stream, a second thread would
    add nothing.

    Shapes: embeddings (N, d) on any device, edges with M candidates -> (M,) float32 (host).
    """
    device = next(model.parameters()).device
    embeddings = embeddings.to(device)
    rows, cols, features = (torch.from_numpy(a).to(device) for a in (edges.rows, edges.cols, edges.features))
    m = rows.shape[0]

    def logits(lo: int, hi: int) -> torch.Tensor:
        with one_torch_thread(), torch.no_grad():
            return model.score_edges(embeddings, rows[lo:hi], cols[lo:hi], features[lo:hi])

    if not parallel or m < SPLIT_EDGES or device.type != "cpu":
        out = logits(0, m)
    else:
        half = max(1, round(m / (2 * EDGE_CHUNK))) * EDGE_CHUNK
        with alongside(logits, half, m) as second:
            first = logits(0, half)
            second.withdraw()  # not begun: the second thread is busy, so it runs here
            out = torch.cat([first, second.result()])
    return torch.sigmoid(out).cpu().numpy()
