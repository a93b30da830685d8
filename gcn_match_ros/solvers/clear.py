"""CLEAR (Fathian, Khosoussi, Tian, Lusk & How, 2020): consistent lifting, embedding and alignment rectification.

1. The association matrix P = (A + Aᵀ)/2 with identity diagonal blocks defines a graph; its
   Laplacian L = D − A is normalised with the degree-plus-one matrix,
   L̃ = (D + I)^-½ L (D + I)^-½.
2. The universe size m is CLEAR's own estimate: the number of eigenvalues of L̃ below 0.5
   (a consistent graph of m cliques has exactly m zero eigenvalues), at least the largest view.
3. The m eigenvectors of the smallest eigenvalues, rows normalised to unit length, embed the
   keypoints; m "pivot" rows, each the least aligned with the pivots chosen before, are the
   cluster centres.
4. Every view assigns its keypoints to distinct centres by the authors' fast sub-optimal
   assignment on the distance 1 − ⟨u, c⟩ (each round, every free centre goes to the closest
   unassigned keypoint that chose it). Keypoints sharing a centre form a track, so the
   answer is cycle-consistent by construction.

Everything is exact and computed per connected component of the graph (the binary
nearest-neighbour graphs fall apart into small components); the largest component is
decomposed densely and must not exceed ``max_nodes``.

Faithfulness note: like the original, a keypoint whose component has no free centre left in
its view is assigned to the first free centre of *another* component (distance exactly 1),
which matches it to unrelated keypoints. ``isolate=True`` (not the default) leaves such
keypoints unmatched instead.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from ..rounding import relabel_tracks, tracks_to_pairs
from ._sync import check_inputs, check_spectral_settings, component_eigh, parse_universe, sparse_soft_matches
from .base import SoftMatches, Solver, SolverConfig
from .registry import register

__all__ = ["clear", "clear_embedding", "CLEARConfig", "CLEARSolver"]

_SOFT = ("binary", "embedding")


def clear_embedding(adjacency, view_offsets, universe_size="est", max_nodes: int = 6000):
    """Steps 1–3: the row-normalised embedding U (N×m, CSR) and m.

    ``universe_size="est"`` uses CLEAR's own estimate (eigenvalues of L̃ below 0.5).
    """
    a, offs = check_inputs(adjacency, view_offsets, method="clear")
    n = a.shape[0]
    deg = np.asarray(a.sum(axis=1)).ravel()
    lap = sp.diags(deg) - a
    scale = sp.diags(1.0 / np.sqrt(deg + 1.0))
    lnrm = sp.csr_matrix(scale @ lap @ scale)
    eig = component_eigh(lnrm, max_nodes=max_nodes, method="clear")
    m = parse_universe(universe_size, method="clear")
    if m is None:
        # An eigenvalue of exactly 0.5 is structural (a path a–b–c of three keypoints has one):
        # count "below 0.5" with a margin so that rounding noise cannot decide it.
        m = int((eig.values < 0.5 - 1e-9).sum())
        m = max(m, int(np.max(np.diff(offs))) if n else 0)
    m = int(min(max(m, 1), n)) if n else 0
    idx = np.argsort(np.round(eig.values, 10), kind="stable")[:m]
    u = sp.csr_matrix(eig.vectors[:, idx])
    norm = np.sqrt(np.asarray(u.multiply(u).sum(axis=1)).ravel())
    u = sp.csr_matrix(sp.diags(1.0 / np.maximum(norm, 1e-300)) @ u)
    return u, m, offs


def _pivot_rows(u: sp.csr_matrix, m: int) -> np.ndarray:
    """Indices of m pivot rows: the first row, then repeatedly the row whose summed |inner
    product| with the pivots so far is smallest (first index on ties)."""
    n = u.shape[0]
    gram = sp.csc_matrix(abs(u @ u.T))
    total = np.zeros(n)
    chosen = np.zeros(n, bool)
    piv = np.empty(m, np.int64)
    cur = 0
    for k in range(m):
        piv[k] = cur
        chosen[cur] = True
        col = gram.getcol(cur)
        total[col.indices] += col.data
        if k + 1 < m:
            masked = np.where(chosen, np.inf, total)
            cur = int(np.argmin(masked))
    return piv


def _suboptimal_assign(f: np.ndarray) -> np.ndarray:
    """The authors' fast assignment of rows (keypoints of one view) to distinct columns.

    Each round every unassigned row picks its closest free column; a column picked by several
    rows goes to the closest of them (first on ties); losers retry in the next round.
    Requires n_rows <= n_cols. Returns (n_rows,) column of every row.
    """
    nr, nc = f.shape
    f = f.astype(np.float64, copy=True)
    assign = np.full(nr, -1, np.int64)
    while np.any(assign < 0):
        rows = np.flatnonzero(assign < 0)
        sub = f[rows]
        pick = np.argmin(sub, axis=1)
        val = sub[np.arange(rows.size), pick]
        order = np.lexsort((rows, val, pick))  # by column, then distance, then row index
        first = np.r_[True, pick[order][1:] != pick[order][:-1]]
        win = order[first]
        assign[rows[win]] = pick[win]
        f[:, pick[win]] = np.inf
    return assign


def clear_labels(u: sp.csr_matrix, m: int, offs: np.ndarray, isolate: bool = False) -> np.ndarray:
    """Step 4: the centre (universe point) of every keypoint; -1 where ``isolate`` drops it."""
    n = u.shape[0]
    piv = _pivot_rows(u, m)
    c = u[piv]
    labels = np.full(n, -1, np.int64)
    for v in range(len(offs) - 1):
        lo, hi = int(offs[v]), int(offs[v + 1])
        if hi == lo:
            continue
        sim = (u[lo:hi] @ c.T).toarray()
        assign = _suboptimal_assign(1.0 - sim)
        if isolate:
            ok = sim[np.arange(hi - lo), assign] > 1e-9
            assign = np.where(ok, assign, -1)
        labels[lo:hi] = assign
    return labels


def clear(adjacency, view_offsets, universe_size="est", max_nodes: int = 6000, isolate: bool = False) -> np.ndarray:
    """CLEAR multi-view matching.

    Args:
        adjacency: (N, N) scipy.sparse matrix or ndarray of pairwise association scores in [0, 1]
            (diagonal and within-view blocks ignored: identity blocks as in the paper).
        view_offsets: (V+1,) keypoints of view v are ``view_offsets[v]:view_offsets[v+1]``.
        universe_size: ``"est"`` (CLEAR's estimate from the normalised Laplacian) or m.
        max_nodes: largest connected component decomposed densely.
        isolate: leave keypoints unmatched when their only free centre is unrelated (similarity 0).

    Returns:
        (N,) int64 track ids, at most one keypoint per view per track (-1: unmatched).
    """
    u, m, offs = clear_embedding(adjacency, view_offsets, universe_size, max_nodes)
    return relabel_tracks(clear_labels(u, m, offs, isolate))


@dataclasses.dataclass
class CLEARConfig(SolverConfig):
    """Settings of :class:`CLEARSolver`.

    Attributes:
        graph: input graph (the reference fed the original the binary mutual-NN graph, with or
            without Lowe's ratio 0.8).
        threshold: unused (CLEAR rounds itself); kept for the common interface.
        universe: ``"est"`` (CLEAR's own estimate) or the number of scene points.
        soft: pair scores: ``"binary"`` (1 for pairs in one track, as the original outputs
            X Xᵀ) or ``"embedding"`` (the cosine of the embedding rows, clamped to [0, 1]).
        isolate: see :func:`clear`.
        max_nodes: largest connected component decomposed densely (refused above).
    """

    graph: str = "ratio0.8"
    threshold: float = 0.5
    universe: str = "est"
    soft: str = "binary"
    isolate: bool = False
    max_nodes: int = 6000

    def __post_init__(self) -> None:
        super().__post_init__()
        check_spectral_settings(self, _SOFT, method="clear")


@register
class CLEARSolver(Solver):
    """Fathian et al. 2020: spectral embedding of the normalised Laplacian, per-view assignment to pivots."""

    name = "clear"
    Config = CLEARConfig

    def match(self, problem: Problem, graph: CorrespondenceGraph, similarity: DescriptorSimilarity):
        cfg = self.config
        u, m, offs = clear_embedding(graph.adjacency(), graph.view_offsets, cfg.universe, cfg.max_nodes)
        track = relabel_tracks(clear_labels(u, m, offs, cfg.isolate))
        if cfg.soft == "binary":
            r, c = tracks_to_pairs(track)
            soft = SoftMatches(r, c, np.ones(r.size, np.float32))
        else:
            soft = sparse_soft_matches(u @ u.T, offs)
        return soft, track
