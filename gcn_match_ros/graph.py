"""The correspondence graph of a window of views.

Nodes are the keypoints of all views; a weighted edge joins two keypoints of
*different* views whose descriptors are similar. The paper's construction
(Phillips & Daniilidis 2019, Sec. 4) is:

1. cosine similarity of L2-normalised descriptors between every pair of views,
2. min–max rescale of all cross-view similarities to [0, 1],
3. keep the top-k entries of every row inside each view-pair block,
4. symmetrise with max, zero the within-view blocks.

It is computed one view-pair block at a time and only the kept entries are
stored, so memory grows with the number of edges, never with N². Options that
users of descriptor matching expect — mutual nearest neighbours, Lowe's ratio
test, a similarity floor, binary weights — select a subset of the same candidates.
"""
from __future__ import annotations

import dataclasses
from typing import Dict, Optional

import numpy as np
import scipy.sparse as sp

from .configs import JsonConfig
from .descriptors import NORMALIZATIONS, cosine_distance
from .problem import Problem
from .similarity import DescriptorSimilarity

__all__ = ["GraphConfig", "GRAPH_PRESETS", "CorrespondenceGraph", "build_graph"]


@dataclasses.dataclass(frozen=True)
class GraphConfig(JsonConfig):
    """How candidate edges are chosen and weighted.

    Attributes:
        k: candidates kept per keypoint in every other view (top-k of its row in the block).
        mutual: keep an edge only if each end is among the other's top-k (else: either).
        ratio: Lowe's ratio threshold on descriptor distances (best / second best
            in that view), applied to the row's candidates; None disables it.
        min_similarity: drop edges whose rescaled similarity is below this floor.
        rescale: "minmax" (the paper: over all cross-view similarities) or "none"
            (weights are the cosine clipped to [0, 1]).
        binary: weights 1 for every kept edge (the input of the synchronisation baselines).
        normalization: "l2" or "rootsift" (Hellinger: L1-normalise, sqrt) before the cosine.
    """

    k: int = 4
    mutual: bool = False
    ratio: Optional[float] = None
    min_similarity: float = 0.0
    rescale: str = "minmax"
    binary: bool = False
    normalization: str = "l2"

    def __post_init__(self) -> None:
        if self.k < 1:
            raise ValueError(f"GraphConfig.k must be >= 1, got {self.k}")
        if self.ratio is not None and not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"GraphConfig.ratio must be in (0, 1], got {self.ratio}")
        if self.rescale not in ("minmax", "none"):
            raise ValueError(f"GraphConfig.rescale must be 'minmax' or 'none', got {self.rescale!r}")
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"GraphConfig.normalization must be 'l2' or 'rootsift', got {self.normalization!r}")

    @classmethod
    def paper(cls, k: int = 4) -> "GraphConfig":
        """Soft top-k graph of the paper."""
        return cls(k=k)

    @classmethod
    def mutual_nn(cls, ratio: Optional[float] = None) -> "GraphConfig":
        """Binary mutual-nearest-neighbour graph (optionally with Lowe's ratio test)."""
        return cls(k=1, mutual=True, ratio=ratio, binary=True, rescale="none")


#: Named input graphs; solver settings select one with ``graph=<name>``.
GRAPH_PRESETS: Dict[str, GraphConfig] = {
    "knn4": GraphConfig.paper(4),
    "knn8": GraphConfig.paper(8),
    "mutual": GraphConfig.mutual_nn(),
    "ratio0.8": GraphConfig.mutual_nn(0.8),
    "mutual-soft": GraphConfig(k=1, mutual=True, rescale="none"),
    "ratio0.8-soft": GraphConfig(k=1, mutual=True, ratio=0.8, rescale="none"),
}


@dataclasses.dataclass
class CorrespondenceGraph:
    """Symmetric sparse graph over the keypoints of V views (no within-view edges).

    Every undirected edge is stored in both directions, sorted by (row, col).

    Shapes:
        view_offsets: (V+1,) int64.
        rows, cols: (E,) int64 node indices.
        weights: (E,) float32 adjacency weight in [0, 1].
        cosine: (E,) float32 raw descriptor cosine similarity of the edge.
        ratio: (E,) float32 Lowe ratio of the edge, min over both ends
            (distance to this neighbour / distance to the second-nearest in that view; 1 if none).
        rank: (E,) int64 rank of the edge among its end's candidates in that view (0 = best), min over both ends.
    """

    view_offsets: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    weights: np.ndarray
    cosine: np.ndarray
    ratio: np.ndarray
    rank: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.view_offsets[-1])

    @property
    def n_views(self) -> int:
        return int(self.view_offsets.shape[0] - 1)

    @property
    def n_edges(self) -> int:
        """Number of stored (directed) edges: twice the undirected count."""
        return int(self.rows.shape[0])

    @property
    def view_index(self) -> np.ndarray:
        return np.repeat(np.arange(self.n_views, dtype=np.int64), np.diff(self.view_offsets))

    def adjacency(self, values: Optional[np.ndarray] = None, add_identity: bool = False) -> sp.csr_matrix:
        """(N, N) scipy CSR adjacency with ``values`` (default: weights) and optional identity."""
        n = self.n_nodes
        vals = self.weights if values is None else values
        a = sp.csr_matrix((vals.astype(np.float64), (self.rows, self.cols)), shape=(n, n))
        if add_identity:
            a = a + sp.identity(n, format="csr")
        return a

    def upper_pairs(self):
        """Undirected edges once: (rows, cols, edge positions) with rows < cols."""
        keep = np.flatnonzero(self.rows < self.cols)
        return self.rows[keep], self.cols[keep], keep


def _directed_candidates(best: np.ndarray, idx: np.ndarray, k: int, row_offset: int, col_offset: int):
    """Candidate edges from every row of a similarity block to its top-k columns.

    Args:
        best, idx: (n_rows, >= min(k, n_cols)) the row's largest similarities and their columns,
            best first (:func:`gcn_match_ros.similarity.most_similar`); a second column, where
            the block has one, gives the ratio test (else ratio 1).

    Returns (rows, cols, cosine, ratio, rank), each of length n_rows * min(k, n_cols).
    """
    n_rows = idx.shape[0]
    second = best[:, 1] if best.shape[1] >= 2 else np.full(n_rows, -1.0, np.float32)
    kk = min(k, best.shape[1])
    best, idx = best[:, :kk], idx[:, :kk]
    ratio = np.where(second[:, None] > -1.0,
                     cosine_distance(best) / np.maximum(cosine_distance(second)[:, None], 1e-12), 1.0)
    return (np.repeat(np.arange(n_rows, dtype=np.int64) + row_offset, kk),
            idx.ravel() + col_offset,
            best.ravel().astype(np.float32),
            np.minimum(ratio, 1.0).ravel().astype(np.float32),
            np.tile(np.arange(kk, dtype=np.int64), n_rows))


def build_graph(problem: Problem, config: GraphConfig = GraphConfig(),
                similarity: Optional[DescriptorSimilarity] = None) -> CorrespondenceGraph:
    """Build the correspondence graph of ``problem`` block by block.

    Each unordered view pair's similarity block (``similarity``, the window's shared
    :class:`~gcn_match_ros.similarity.DescriptorSimilarity`; made here if None) serves both
    directions and the min–max range; only candidates are kept, so memory is O(E) plus the
    blocks the similarity keeps.
    """
    similarity = similarity if similarity is not None else DescriptorSimilarity(problem)
    offs = problem.view_offsets
    sizes = problem.view_sizes
    V = problem.n_views
    n = problem.n_keypoints
    parts = []
    sim_lo, sim_hi = np.inf, -np.inf
    for i in range(V):
        for j in range(i + 1, V):
            if sizes[i] == 0 or sizes[j] == 0:
                continue
            sim = similarity.block(i, j, config.normalization).numpy()
            sim_lo, sim_hi = min(sim_lo, float(sim.min())), max(sim_hi, float(sim.max()))
            # k + 1 >= 2 best of each row and column: the candidates and the ratio test's second
            best_r, idx_r, best_c, idx_c = similarity.most_similar(i, j, config.normalization,
                                                                   min(max(config.k, 2), sim.shape[1]),
                                                                   min(max(config.k, 2), sim.shape[0]))
            parts.append(_directed_candidates(best_r, idx_r, config.k, offs[i], offs[j]))
            parts.append(_directed_candidates(best_c, idx_c, config.k, offs[j], offs[i]))
    if not parts:
        empty_i, empty_f = np.zeros(0, np.int64), np.zeros(0, np.float32)
        return CorrespondenceGraph(offs.copy(), empty_i, empty_i.copy(), empty_f, empty_f.copy(),
                                   empty_f.copy(), empty_i.copy())
    rows, cols, cos, rat, rnk = (np.concatenate(a) for a in zip(*parts))
    if config.ratio is not None:
        keep = rat < config.ratio
        rows, cols, cos, rat, rnk = rows[keep], cols[keep], cos[keep], rat[keep], rnk[keep]

    # Merge the two directions of a pair; `count` says how many ends proposed it.
    # (a sort and reduceat: np.unique with inverse and counts and np.minimum.at took 4x longer;
    # numpy's default sort, as the copies of a key carry the same cosine and are reduced by
    # their minimum: a stable sort of 24 k keys took 1.9 ms, the default 0.4)
    key = np.minimum(rows, cols) * n + np.maximum(rows, cols)
    order = np.argsort(key)
    key = key[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]]) if key.size else np.zeros(0, np.int64)
    uniq = key[starts]
    count = np.diff(np.r_[starts, key.size])
    u_cos = cos[order][starts]  # the same value from both directions
    u_rat = np.minimum.reduceat(rat[order], starts) if key.size else rat[:0]
    u_rnk = np.minimum.reduceat(rnk[order], starts) if key.size else rnk[:0]
    u_lo, u_hi = uniq // n, uniq % n

    if config.rescale == "minmax":
        w = (u_cos - sim_lo) / max(sim_hi - sim_lo, 1e-12)
    else:
        w = u_cos
    w = np.clip(w, 0.0, 1.0).astype(np.float32)
    keep = w >= config.min_similarity
    if config.mutual:
        keep &= count >= 2
    if config.binary:
        w = np.ones_like(w)
    u_lo, u_hi, w, u_cos, u_rat, u_rnk = (a[keep] for a in (u_lo, u_hi, w, u_cos, u_rat, u_rnk))

    rows = np.concatenate([u_lo, u_hi])
    cols = np.concatenate([u_hi, u_lo])
    order = np.argsort(rows * n + cols)  # unique keys: the (row, col) order (np.lexsort: 10x slower)

    def both(a: np.ndarray) -> np.ndarray:
        return np.concatenate([a, a])[order]

    return CorrespondenceGraph(offs.copy(), rows[order], cols[order], both(w), both(u_cos),
                               both(u_rat), both(u_rnk))
