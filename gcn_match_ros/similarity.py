"""Descriptor similarity of a window's view pairs, computed once per pair and shared.

The correspondence graph (:func:`gcn_match_ros.graph.build_graph`), the candidate edges
(:func:`gcn_match_ros.edges.candidates.candidate_edges`) and the descriptor fallback of the
``gcn`` solver all read cosine similarities of one view pair's descriptors. A
:class:`DescriptorSimilarity` made for the window computes each ``(normalization, i, j)``
block once, on first use, and hands the same tensor to every later reader. Blocks are kept
up to ``budget_bytes`` (least recently used go first), so a huge window's memory stays
bounded; a block evicted and asked for again is computed again (``recomputed`` counts it).
Two threads may read one window's blocks at once (the ``gcn`` solver's graph and candidate
edges, :func:`gcn_match_ros.threads.alongside`): the cache is guarded by a lock, the products
run outside it.

A block's best rows and columns (:meth:`DescriptorSimilarity.most_similar`) are shared the
same way: computed once per view pair, at the largest k asked for or declared (``top_k``), so
the graph's top-4 lists are the first columns of the candidate edges' top-11 when both read
the same normalization. A list being computed is waited for, not computed again.

Different normalizations are different similarities: a window whose graph reads L2-normalised
descriptors and whose candidates read RootSIFT ones has two blocks per view pair, each
computed once.
"""
from __future__ import annotations

import collections
import threading
from typing import Dict, Mapping, Optional, Tuple

import numba
import numpy as np
import torch

from .descriptors import NORMALIZATIONS, normalize_descriptors
from .problem import Problem
from .timing import stage

__all__ = ["DescriptorSimilarity", "most_similar"]

Key = Tuple[str, int, int]


class DescriptorSimilarity:
    """Cosine similarity blocks of one problem's view pairs (see the module docstring).

    Args:
        problem: the window.
        budget_bytes: most bytes of blocks kept at once.
        top_k: normalization -> the k that :meth:`most_similar` computes at least, for a reader
            that will ask for more than the first one does.

    Attributes:
        computed, recomputed: blocks computed, and of those computed again after eviction.
    """

    def __init__(self, problem: Problem, budget_bytes: int = 256 * 2**20,
                 top_k: Optional[Mapping[str, int]] = None) -> None:
        self._descriptors = problem.descriptors
        self._offsets = problem.view_offsets
        self._budget = int(budget_bytes)
        self._top_k = dict(top_k or {})
        self._normalized: Dict[str, torch.Tensor] = {}
        self._blocks: "collections.OrderedDict[Key, torch.Tensor]" = collections.OrderedDict()
        self._seen: set = set()
        self._bytes = 0
        self._lock = threading.Lock()
        self._best: Dict[Key, Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._best_pending: Dict[Key, threading.Event] = {}
        self.computed = 0
        self.recomputed = 0

    def normalized(self, normalization: str) -> torch.Tensor:
        """(N, D) float32 unit rows (:func:`descriptors.normalize_descriptors`), computed once."""
        if normalization not in NORMALIZATIONS:
            raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
        d = self._normalized.get(normalization)
        if d is None:
            with stage("similarity"):
                d = torch.from_numpy(normalize_descriptors(self._descriptors, normalization))
            with self._lock:
                d = self._normalized.setdefault(normalization, d)
        return d

    def view(self, v: int, normalization: str) -> torch.Tensor:
        """(n_v, D) normalised descriptors of view v."""
        return self.normalized(normalization)[int(self._offsets[v]):int(self._offsets[v + 1])]

    def block(self, i: int, j: int, normalization: str) -> torch.Tensor:
        """(n_i, n_j) float32 cosines between views i and j; ``block(j, i)`` is its transpose,
        the same memory."""
        if i > j:
            return self.block(j, i, normalization).T
        key = (normalization, int(i), int(j))
        with self._lock:
            blk = self._blocks.get(key)
            if blk is not None:
                self._blocks.move_to_end(key)
                return blk
        di, dj = self.view(i, normalization), self.view(j, normalization)
        with stage("similarity"):
            blk = di @ dj.T
        with self._lock:
            return self._keep(key, blk)

    def most_similar(self, i: int, j: int, normalization: str, k_row: int, k_col: int
                     ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:func:`most_similar` of ``block(i, j)``: the ``k_row`` best entries of every row and
        the ``k_col`` best of every column, computed once per view pair (module docstring).

        Returns: row values (n_i, k_row) float32, row indices (n_i, k_row) int64, column values
        (n_j, k_col), column indices (n_j, k_col) — views of the cached lists.
        """
        if i > j:
            col_val, col_idx, row_val, row_idx = self.most_similar(j, i, normalization, k_col, k_row)
            return row_val, row_idx, col_val, col_idx
        key = (normalization, int(i), int(j))
        while True:
            with self._lock:
                best = self._best.get(key)
                if best is not None and best[0].shape[1] >= k_row and best[2].shape[1] >= k_col:
                    break
                pending = self._best_pending.get(key)
                if pending is None:
                    pending = self._best_pending[key] = threading.Event()
                    mine = True
                else:
                    mine = False
            if not mine:
                pending.wait()
                continue
            try:
                sim = self.block(i, j, normalization).numpy()
                declared = self._top_k.get(normalization, 0)
                best = most_similar(sim, min(max(k_row, declared), sim.shape[1]),
                                    min(max(k_col, declared), sim.shape[0]))
                with self._lock:
                    self._best[key] = best
            finally:
                with self._lock:
                    del self._best_pending[key]
                pending.set()
            break
        row_val, row_idx, col_val, col_idx = best
        return row_val[:, :k_row], row_idx[:, :k_row], col_val[:, :k_col], col_idx[:, :k_col]

    def _keep(self, key: Key, blk: torch.Tensor) -> torch.Tensor:
        """Cache a block just computed (the lock held); the copy another thread cached first wins."""
        cached = self._blocks.get(key)
        if cached is not None:
            return cached
        self.computed += 1
        if key in self._seen:
            self.recomputed += 1
        self._seen.add(key)
        size = blk.numel() * blk.element_size()
        if size <= self._budget:
            self._blocks[key] = blk
            self._bytes += size
            while self._bytes > self._budget:
                _, old = self._blocks.popitem(last=False)
                self._bytes -= old.numel() * old.element_size()
        return blk

    @property
    def cached_bytes(self) -> int:
        return self._bytes

    def __repr__(self) -> str:
        return (f"DescriptorSimilarity({len(self._offsets) - 1} views, {len(self._blocks)} blocks cached, "
                f"{self.computed} computed, {self.recomputed} recomputed)")


def most_similar(sim: np.ndarray, k_row: int, k_col: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ``k_row`` largest entries of every row and the ``k_col`` largest of every column of a
    similarity block, best first, the lower index first among equal values.

    Compiled, on the calling thread: inside a window's solve torch.topk cost ~0.2 ms a call even
    on a 200 x 200 block (its thread pool wakes for every call; an 8-camera window made 168
    calls, 33 of its 120 ms), and above k = 7 it switches to a ~5x slower kernel. A first pass
    bounds every row's and column's k-th best from below (:func:`_kth_best_bounds`), so the
    second pass sorts in only the few entries that can make a list (500 x 500, k = 11: ~17 a row
    instead of ~54). A transposed block is read as its contiguous original. 500 x 500, k = 11:
    1.35 ms with no bounds, 0.92 with them, 0.68 since the bounds take 16-lane steps and the
    second pass marks an entry's hits in a vectorised loop before collecting them.

    Args:
        sim: (n, m) float32, finite.
        k_row, k_col: at most m and n.

    Returns:
        row values (n, k_row) float32, row indices (n, k_row) int64, column values (m, k_col),
        column indices (m, k_col).
    """
    n, m = sim.shape
    if not (0 < k_row <= m and 0 < k_col <= n):
        raise ValueError(f"most_similar: k_row={k_row}, k_col={k_col} for a {n} x {m} block")
    sim = np.asarray(sim, np.float32)
    if not sim.flags.c_contiguous and sim.T.flags.c_contiguous:
        col_val, col_idx, row_val, row_idx = _most_similar(sim.T, int(k_col), int(k_row))
        return row_val, row_idx, col_val, col_idx
    return _most_similar(np.ascontiguousarray(sim), int(k_row), int(k_col))


#: Chunks whose maxima bound a row's (column's) k-th best, for k up to this many: 16 float32
#: lanes, one AVX-512 register (a literal in the loops below, so that they vectorise; 16 was
#: also the fastest count at 500 x 500, k = 4 and 11). A larger k, or fewer entries than
#: chunks, gets no bound (every entry is sorted in: exact, slower; the solvers ask for <= 11).
_BOUND_CHUNKS = 16


@numba.njit(cache=True, nogil=True)
def _most_similar(sim, k_row, k_col):
    n, m = sim.shape
    row_bound, col_bound = _kth_best_bounds(sim, k_row, k_col)
    row_val = np.full((n, k_row), -np.inf, np.float32)
    row_idx = np.zeros((n, k_row), np.int64)
    col_val = np.full((m, k_col), -np.inf, np.float32)
    col_idx = np.zeros((m, k_col), np.int64)
    col_floor = np.full(m, -np.inf, np.float32)  # each column's k-th best so far, contiguous
    marks = np.empty(m, np.uint8)
    hits = np.empty(m + 1, np.int64)
    for i in range(n):
        row = sim[i]
        bound = row_bound[i]
        _mark_hits(marks, row, bound, col_bound)
        # the marked entries, in order; collected without branches
        n_hits = 0
        for j in range(m):
            hits[n_hits] = j
            n_hits += marks[j] != 0
        row_floor = np.float32(-np.inf)
        for t in range(n_hits):
            j = hits[t]
            v = row[j]
            if marks[j] & 1 and v > row_floor:
                row_floor = _insert(row_val[i], row_idx[i], v, j)
            if marks[j] & 2 and v > col_floor[j]:
                col_floor[j] = _insert(col_val[j], col_idx[j], v, i)
    return row_val, row_idx, col_val, col_idx


@numba.njit(cache=True, nogil=True, inline="always")
def _mark_hits(marks, row, bound, col_bound):
    """marks[j] = 1 if row[j] reaches the row's bound, + 2 if it reaches column j's: a loop
    without branches, which vectorises."""
    for j in range(row.shape[0]):
        v = row[j]
        marks[j] = np.uint8(v >= bound) | (np.uint8(v >= col_bound[j]) << np.uint8(1))


@numba.njit(cache=True, nogil=True)
def _kth_best_bounds(sim, k_row, k_col):
    """Lower bounds of every row's k_row-th and every column's k_col-th largest entry: the k-th
    largest of the maxima of :data:`_BOUND_CHUNKS` disjoint chunks (k chunks each hold an entry
    at least that large); -inf where k is larger or there are fewer entries. Rows are chunked by
    column modulo 16 and columns by row modulo 16, so every maximum is an elementwise maximum of
    contiguous runs, and both come from one read of the block.

    Shapes: sim (n, m) C-contiguous -> (n,), (m,) float32.
    """
    n, m = sim.shape
    row_bound = np.full(n, -np.inf, np.float32)
    col_bound = np.full(m, -np.inf, np.float32)
    by_row = k_row <= _BOUND_CHUNKS <= m
    by_col = k_col <= _BOUND_CHUNKS <= n
    lanes = np.empty(_BOUND_CHUNKS, np.float32)
    col_maxima = sim[:_BOUND_CHUNKS].copy() if by_col else sim[:0].copy()
    whole = m - m % _BOUND_CHUNKS
    for i in range(n):
        row = sim[i]
        if by_row:
            for c in range(_BOUND_CHUNKS):
                lanes[c] = row[c]
            for start in range(_BOUND_CHUNKS, whole, _BOUND_CHUNKS):
                for c in range(_BOUND_CHUNKS):
                    lanes[c] = max(lanes[c], row[start + c])
            for j in range(whole, m):
                lanes[j - whole] = max(lanes[j - whole], row[j])
            row_bound[i] = _kth_largest16(lanes, k_row)
        if by_col and i >= _BOUND_CHUNKS:
            maxima = col_maxima[i % _BOUND_CHUNKS]
            for j in range(m):
                maxima[j] = max(maxima[j], row[j])
    if by_col:
        for j in range(m):
            for c in range(_BOUND_CHUNKS):
                lanes[c] = col_maxima[c, j]
            col_bound[j] = _kth_largest16(lanes, k_col)
    return row_bound, col_bound


@numba.njit(cache=True, inline="always")
def _kth_largest16(values, k):
    """The k-th largest of the 16 ``values``: the smallest value that fewer than k others beat
    (256 comparisons without branches: faster than sorting 16 into a list of k)."""
    kth = np.float32(np.inf)
    for t in range(_BOUND_CHUNKS):
        v = values[t]
        beaten_by = 0
        for u in range(_BOUND_CHUNKS):
            beaten_by += values[u] > v
        if beaten_by < k and v < kth:
            kth = v
    return kth


@numba.njit(cache=True, inline="always")
def _insert(values, indices, v, at):
    """Insert ``v`` (from position ``at``) into the descending list ``values`` / ``indices``,
    after any equal values; the last entry falls out. Returns the new last value."""
    t = values.shape[0] - 1
    while t > 0 and v > values[t - 1]:
        values[t] = values[t - 1]
        indices[t] = indices[t - 1]
        t -= 1
    values[t] = v
    indices[t] = at
    return values[values.shape[0] - 1]
