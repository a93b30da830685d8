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
from typing import Dict, Optional, Tuple

import numba
import numpy as np
import scipy.sparse as sp

from .configs import JsonConfig
from .descriptors import NORMALIZATIONS, cosine_distance32
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


@numba.njit(cache=True, nogil=True)
def _directed_candidates(best, idx, k, row_offset, col_offset, rows, cols, cosine, ratio, rank, at):
    """Write the candidate edges from every row of a similarity block to its top-k columns into
    the output arrays from position ``at``; returns the position after them.

    Args:
        best, idx: (n_rows, >= min(k, n_cols)) the row's largest similarities and their columns,
            best first (:func:`gcn_match_ros.similarity.most_similar`); a second column, where
            the block has one, gives the ratio test (else ratio 1).
        rows, cols (int64), cosine, ratio (float32), rank (int64): (M,) outputs, written at
            ``at`` ... ``at + n_rows * min(k, best.shape[1])``: the row's keypoint, the column's,
            their similarity, the ratio (cosine distance to this neighbour / to the second best,
            ``descriptors.cosine_distance`` in float32 as numpy computes it, at most 1) and the
            neighbour's rank in the row (0 = best).
    """
    n_rows = idx.shape[0]
    kk = min(k, best.shape[1])
    tiny, one = np.float32(1e-12), np.float32(1.0)
    for r in range(n_rows):
        has_second = best.shape[1] >= 2 and best[r, 1] > -1.0
        second = cosine_distance32(best[r, 1]) if has_second else one
        for c in range(kk):
            value = best[r, c]
            q = one
            if has_second:
                q = min(cosine_distance32(value) / max(second, tiny), one)
            rows[at], cols[at] = r + row_offset, idx[r, c] + col_offset
            cosine[at], ratio[at], rank[at] = value, q, c
            at += 1
    return at


@numba.njit(cache=True, nogil=True)
def _merged_both_ways(n, rows, cols, cosine, ratio, rank):
    """The directed candidates (rows[m] -> cols[m]) as the graph's entries: every pair once in
    each direction, sorted by (row, col); a pair proposed from both ends is one entry per
    direction with the lower ratio and rank and the count of its proposals (1 or 2). The cosine
    is the same from both ends.

    Each proposal is two slots, one from each end; two stable counting sorts put them in order,
    by column and then by row, so a pair's slots come out side by side. Against one counting sort
    by row and an insertion sort of each row's ~2 k (V - 1) slots, timed call by call in the solve:
    4 x 500 0.79 against 1.01 ms, 4 x 1000 1.73 against 1.90, 8 x 500 5.1-5.9 against 5.5-5.8, but
    10 x 1000 22.9 against 20.4 (its 720 k slots scatter over more memory than the caches hold).

    Shapes: (M,) each -> rows, cols (E,) int64, cosine, ratio (E,) float32, rank, count (E,) int64.
    """
    m = rows.shape[0]
    # a node has as many slots as a row as it has as a column: one count serves both sorts
    start = np.zeros(n + 1, np.int64)
    for e in range(m):
        start[rows[e] + 1] += 1
        start[cols[e] + 1] += 1
    for v in range(n):
        start[v + 1] += start[v]
    # slot e < m: rows[e] -> cols[e]; slot m + e: cols[e] -> rows[e]
    fill = start[:-1].copy()
    by_col = np.empty(2 * m, np.int64)
    for e in range(m):
        by_col[fill[cols[e]]] = e
        fill[cols[e]] += 1
        by_col[fill[rows[e]]] = m + e
        fill[rows[e]] += 1
    fill = start[:-1].copy()
    by_row = np.empty(2 * m, np.int64)
    for t in range(2 * m):
        s = by_col[t]
        r = rows[s] if s < m else cols[s - m]
        by_row[fill[r]] = s
        fill[r] += 1
    out_rows = np.empty(2 * m, np.int64)
    out_cols = np.empty(2 * m, np.int64)
    out_cos = np.empty(2 * m, np.float32)
    out_ratio = np.empty(2 * m, np.float32)
    out_rank = np.empty(2 * m, np.int64)
    out_count = np.empty(2 * m, np.int64)
    size = 0
    for t in range(2 * m):
        s = by_row[t]
        e = s if s < m else s - m
        r, c = (rows[e], cols[e]) if s < m else (cols[e], rows[e])
        if size > 0 and out_rows[size - 1] == r and out_cols[size - 1] == c:
            out_ratio[size - 1] = min(out_ratio[size - 1], ratio[e])
            out_rank[size - 1] = min(out_rank[size - 1], rank[e])
            out_count[size - 1] += 1
        else:
            out_rows[size], out_cols[size] = r, c
            out_cos[size], out_ratio[size], out_rank[size], out_count[size] = cosine[e], ratio[e], rank[e], 1
            size += 1
    return (out_rows[:size], out_cols[:size], out_cos[:size], out_ratio[:size], out_rank[:size],
            out_count[:size])


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
    blocks = []
    sim_lo, sim_hi = np.inf, -np.inf
    for i in range(V):
        for j in range(i + 1, V):
            if sizes[i] == 0 or sizes[j] == 0:
                continue
            sim = similarity.block(i, j, config.normalization).numpy()
            sim_lo, sim_hi = min(sim_lo, float(sim.min())), max(sim_hi, float(sim.max()))
            # k + 1 >= 2 best of each row and column: the candidates and the ratio test's second
            blocks.append((i, j) + similarity.most_similar(i, j, config.normalization,
                                                           min(max(config.k, 2), sim.shape[1]),
                                                           min(max(config.k, 2), sim.shape[0])))
    total = sum(best_r.shape[0] * min(config.k, best_r.shape[1]) + best_c.shape[0] * min(config.k, best_c.shape[1])
                for _, _, best_r, _, best_c, _ in blocks)
    rows, cols = np.empty(total, np.int64), np.empty(total, np.int64)
    cos, rat, rnk = np.empty(total, np.float32), np.empty(total, np.float32), np.empty(total, np.int64)
    at = 0
    for i, j, best_r, idx_r, best_c, idx_c in blocks:
        at = _directed_candidates(best_r, idx_r, config.k, offs[i], offs[j], rows, cols, cos, rat, rnk, at)
        at = _directed_candidates(best_c, idx_c, config.k, offs[j], offs[i], rows, cols, cos, rat, rnk, at)
    if config.ratio is not None:
        rows, cols, cos, rat, rnk = _taken(rat < config.ratio, rows, cols, cos, rat, rnk)
    # every pair in both directions, sorted by (row, col); `count`: how many ends proposed it
    rows, cols, cos, rat, rnk, count = _merged_both_ways(n, rows, cols, cos, rat, rnk)
    if config.rescale == "minmax":
        w = (cos - sim_lo) / max(sim_hi - sim_lo, 1e-12)
    else:
        w = cos
    w = np.clip(w, 0.0, 1.0).astype(np.float32)
    keep = w >= config.min_similarity
    if config.mutual:
        keep &= count >= 2
    if config.binary:
        w = np.ones_like(w)
    return CorrespondenceGraph(offs.copy(), *_taken(keep, rows, cols, w, cos, rat, rnk))


def _taken(keep: np.ndarray, *columns: np.ndarray) -> Tuple[np.ndarray, ...]:
    """The entries of ``columns`` where ``keep``: the columns themselves when every entry is kept
    (the learned graph's, which keeps every merged edge: 6 copies of a 4 x 500 window's 37 k entries
    took 0.7 ms), else gathered by index (half the time of boolean indexing).

    Shapes: keep (M,) bool, columns (M,) each -> (K,) each.
    """
    if keep.all():
        return columns
    at = np.flatnonzero(keep)
    return tuple(column.take(at) for column in columns)
