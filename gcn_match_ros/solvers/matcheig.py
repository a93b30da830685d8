"""MatchEIG (Maset, Arrigoni & Fusiello, ICCV 2017): multi-view matching by one eigendecomposition.

The cycle-consistent matrix X Xᵀ has rank d (the number of scene points); MatchEIG takes the d
eigenpairs of largest magnitude of the input Z = A + I, rebuilds Ẑ = U |D| Uᵀ, zeroes entries
below a threshold (0.25) and projects every view-pair block onto a partial permutation with the
authors' greedy rule: candidates are each row's and each column's maximum, accepted from the
largest down while their row and column are free.

The blocks are projected independently, so the answer is *not* cycle-consistent (A↔B and B↔C
may hold without A↔C). As every method here, it is rounded to tracks the shared way: the kept
pairs, scored by Ẑ, go to :func:`~gcn_match_ros.rounding.greedy_tracks` (best first, never two
keypoints of one view in a track). The soft scores for precision–recall are Ẑ clamped to [0, 1].
``rounding="repair", soft="binary"`` is the reference run's protocol instead (connected components
of the kept pairs, surplus keypoints of a view dropped; the binary output as scores): it matches
the reference to 0.002 F1 but loses 0.065 F1 against the greedy rounding on the mutual-NN graph.

d is estimated from the spectrum (:func:`~gcn_match_ros.rounding.estimate_universe_size`). The
eigendecomposition is exact and done per connected component of the input graph; the largest
component must not exceed ``max_nodes``.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from ..graph import CorrespondenceGraph
from ..problem import Problem
from ..similarity import DescriptorSimilarity
from ..rounding import greedy_tracks
from ._sync import (check_inputs, check_spectral_settings, component_eigh, repair_tracks,
                    resolve_universe_size, select_eigvecs, sparse_soft_matches, view_index_of)
from .base import SoftMatches, Solver, SolverConfig
from .registry import register

__all__ = ["matcheig", "matcheig_scores", "matcheig_pairs", "MatchEIGConfig", "MatchEIGSolver"]

_ROUNDING = ("greedy", "repair")
_SOFT = ("zhat", "binary")


def matcheig_scores(adjacency, view_offsets, universe_size="est", max_nodes: int = 6000) -> sp.csr_matrix:
    """Ẑ = U |D| Uᵀ from the d eigenpairs of A + I of largest magnitude.

    Returns:
        (N, N) CSR (block-sparse: zero between different connected components).
    """
    a, offs = check_inputs(adjacency, view_offsets, method="matcheig")
    d = resolve_universe_size(universe_size, a, offs, method="matcheig")
    n = a.shape[0]
    eig = component_eigh(a + sp.identity(n, format="csr"), max_nodes=max_nodes, method="matcheig")
    idx = select_eigvecs(eig, d, "LM")
    u = sp.csr_matrix(eig.vectors[:, idx])
    return sp.csr_matrix(u @ sp.diags(np.abs(eig.values[idx])) @ u.T)


def _greedy_partial_permutation(r: np.ndarray, c: np.ndarray, v: np.ndarray):
    """The authors' greedy projection of one block given its non-zero entries (r, c, v).

    Candidates: for every row its maximum entry, for every column its maximum entry (first
    index on ties), rows' candidates before columns'; accepted from the largest value down
    (stable) when neither the row nor the column is taken yet.
    Returns the accepted (rows, cols).
    """
    if r.size == 0:
        return r, c
    o = np.lexsort((c, -v, r))  # per row: largest value first, then smallest column
    first = np.r_[True, r[o][1:] != r[o][:-1]]
    row_best = o[first]
    o = np.lexsort((r, -v, c))
    first = np.r_[True, c[o][1:] != c[o][:-1]]
    col_best = o[first]
    cand = np.concatenate([row_best, col_best])
    cand = cand[np.argsort(-v[cand], kind="stable")]
    taken_r, taken_c, out = set(), set(), []
    for e in cand:
        rr, cc = int(r[e]), int(c[e])
        if rr in taken_r or cc in taken_c:
            continue
        taken_r.add(rr)
        taken_c.add(cc)
        out.append(e)
    out = np.asarray(out, np.int64)
    return r[out], c[out]


def matcheig_pairs(scores: sp.csr_matrix, view_offsets: np.ndarray, threshold: float = 0.25):
    """Pairs kept by MatchEIG: per view-pair block, entries >= threshold projected greedily.

    Returns:
        (rows, cols, values) with rows < cols (global indices, different views).
    """
    s = sp.triu(scores, k=1).tocoo()
    view = view_index_of(np.asarray(view_offsets, np.int64))
    vr, vc = view[s.row], view[s.col]
    keep = (vr != vc) & (s.data >= threshold)
    if not keep.any():
        z = np.zeros(0, np.int64)
        return z, z.copy(), np.zeros(0)
    r, c, v, vr, vc = s.row[keep], s.col[keep], s.data[keep], vr[keep], vc[keep]
    V = len(view_offsets) - 1
    block = vr * V + vc
    order = np.argsort(block, kind="stable")
    r, c, v, block = r[order], c[order], v[order], block[order]
    bounds = np.flatnonzero(np.r_[True, block[1:] != block[:-1], True])
    out_r, out_c = [], []
    for s0, e0 in zip(bounds[:-1], bounds[1:]):
        rr, cc = _greedy_partial_permutation(r[s0:e0], c[s0:e0], v[s0:e0])
        out_r.append(rr)
        out_c.append(cc)
    rows, cols = np.concatenate(out_r).astype(np.int64), np.concatenate(out_c).astype(np.int64)
    vals = np.asarray(scores[rows, cols]).ravel()
    return rows, cols, vals


def _round(n, view, r, c, v, rounding):
    if rounding == "greedy":
        return greedy_tracks(n, view, r, c, v, threshold=-np.inf)
    return repair_tracks(n, view, r, c, v)


def matcheig(adjacency, view_offsets, universe_size="est", threshold: float = 0.25,
             rounding: str = "greedy", max_nodes: int = 6000) -> np.ndarray:
    """MatchEIG rounded to cycle-consistent tracks.

    Args:
        adjacency: (N, N) scipy.sparse matrix or ndarray of pairwise match scores in [0, 1]
            (diagonal and within-view blocks ignored; identity added).
        view_offsets: (V+1,) keypoints of view v are ``view_offsets[v]:view_offsets[v+1]``.
        universe_size: number of scene points d, or ``"est"``.
        threshold: entries of Ẑ below it are dropped before the block projection (paper: 0.25).
        rounding: ``"greedy"`` (shared greedy conflict-free merging of the kept pairs, best Ẑ
            first) or ``"repair"`` (the reference's protocol: connected components of the kept
            pairs, keeping per view the keypoint with the highest summed Ẑ).
        max_nodes: largest connected component decomposed densely.

    Returns:
        (N,) int64 tracks: MatchEIG's (not cycle-consistent) pairwise answer made consistent.
    """
    if not 0.0 <= threshold <= 1.0:
        raise ValueError(f"matcheig: 'threshold' must be in [0, 1], got {threshold}")
    if rounding not in _ROUNDING:
        raise ValueError(f"matcheig: 'rounding' must be one of {_ROUNDING}, got {rounding!r}")
    z = matcheig_scores(adjacency, view_offsets, universe_size, max_nodes)
    offs = np.asarray(view_offsets, np.int64)
    r, c, v = matcheig_pairs(z, offs, threshold)
    return _round(z.shape[0], view_index_of(offs), r, c, v, rounding)


@dataclasses.dataclass
class MatchEIGConfig(SolverConfig):
    """Settings of :class:`MatchEIGSolver`.

    Attributes:
        graph: input graph (the reference fed the original the binary mutual-NN graph, with or
            without Lowe's ratio 0.8).
        threshold: MatchEIG's threshold on Ẑ (0.25 in the paper).
        universe: ``"est"`` (spectral estimate) or the number of scene points.
        rounding: ``"greedy"`` or ``"repair"`` (see :func:`matcheig`).
        soft: pair scores: ``"zhat"`` (Ẑ clamped to [0, 1]) or ``"binary"`` (1 on the pairs
            MatchEIG keeps: the original's output, what the reference's AP was computed on).
        max_nodes: largest connected component decomposed densely (refused above).
    """

    graph: str = "ratio0.8"
    threshold: float = 0.25
    universe: str = "est"
    rounding: str = "greedy"
    soft: str = "zhat"
    max_nodes: int = 6000

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.rounding not in _ROUNDING:
            raise ValueError(f"rounding must be one of {_ROUNDING}, got {self.rounding!r}")
        check_spectral_settings(self, _SOFT, method="matcheig")


@register
class MatchEIGSolver(Solver):
    """Maset et al. 2017; its pairwise output rounded by the shared greedy merging."""

    name = "matcheig"
    Config = MatchEIGConfig

    def match(self, problem: Problem, graph: CorrespondenceGraph, similarity: DescriptorSimilarity):
        cfg = self.config
        offs = graph.view_offsets
        z = matcheig_scores(graph.adjacency(), offs, cfg.universe, cfg.max_nodes)
        r, c, v = matcheig_pairs(z, offs, cfg.threshold)
        track = _round(graph.n_nodes, graph.view_index, r, c, v, cfg.rounding)
        if cfg.soft == "binary":
            o = np.lexsort((c, r))
            return SoftMatches(r[o], c[o], np.ones(r.size, np.float32)), track
        return sparse_soft_matches(z, offs), track
