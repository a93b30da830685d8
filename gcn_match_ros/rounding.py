"""From soft scores to hard, cycle-consistent tracks — without knowing the number of scene points.

Every method's output is rounded the same way before it is compared (shared/notes/evaluation.md):
pairs are taken from the highest score down and two tracks are merged only when they
share no view (greedy conflict-free merging). The result holds at most one keypoint per
view per track by construction, so it is cycle-consistent, and the number of tracks
comes out of the scores instead of being given.

Methods that need a universe size d up front (spectral, MatchEIG, PGDDS) get it
from :func:`estimate_universe_size`, which reads it off the spectrum of the input graph.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Optional

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

__all__ = ["greedy_tracks", "compile_plain_merge", "MergeTest", "relabel_tracks", "estimate_universe_size",
           "tracks_to_pairs", "track_members", "is_cycle_consistent"]


class MergeTest(NamedTuple):
    """A further test of every merge :func:`greedy_tracks` is about to make, compiled.

    ``test(data, members, n_a, n_b) -> bool`` is a ``numba.njit`` function; ``members`` holds
    the keypoint indices of the two tracks, the first ``n_a`` of one, then the ``n_b`` of the
    other. False refuses the merge (e.g. members that disagree with their views' geometry,
    :class:`gcn_match_ros.edges.consistency.TrackCheck`). ``data``: the tuple it reads.
    """

    test: Callable
    data: tuple


@numba.njit(cache=True)
def _accept_every_merge(data, members, n_a, n_b):
    return True


def greedy_tracks(n_nodes: int, view_index: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                  scores: np.ndarray, threshold: float = 0.5, compatible: Optional[MergeTest] = None) -> np.ndarray:
    """Merge keypoints into tracks from the best-scored pair down, never two of one view.

    Args:
        n_nodes: N.
        view_index: (N,) view of each keypoint.
        rows, cols, scores: (M,) candidate pairs and their scores.
        threshold: pairs scoring below it are never merged.
        compatible: optional further test of each merge (:class:`MergeTest`), asked with the
            members of the two tracks about to be joined.

    Returns:
        (N,) int64 track ids 0..T-1 for keypoints in a track of >= 2 keypoints, -1 otherwise.
    """
    view_index = np.asarray(view_index, np.int64)
    scores = np.asarray(scores)
    keep = np.flatnonzero(scores >= threshold)
    order = keep[np.argsort(-scores[keep], kind="stable")]
    test = compatible if compatible is not None else MergeTest(_accept_every_merge, ())
    roots = _merge_greedily(int(n_nodes), view_index, np.asarray(rows, np.int64)[order],
                            np.asarray(cols, np.int64)[order], int(view_index.max()) + 1 if view_index.size else 1,
                            test.test, test.data)
    return relabel_tracks(roots)


def compile_plain_merge() -> None:
    """Compile :func:`greedy_tracks` without a further test now, not on the first window that
    needs it (chained models of an unverified view pair, the rounding of a method without its
    own): numba cannot cache :func:`_merge_greedily`, which takes a function, and compiling it
    took 0.5-1.5 s of that window (an ORB bag's fourth window in the demo). The matcher node's
    warm-up calls this."""
    greedy_tracks(2, np.array([0, 1]), np.array([0]), np.array([1]), np.array([1.0]))


@numba.njit
def _merge_greedily(n, view, rows, cols, n_views, test, data):
    """Union-find over the pairs in order; two tracks merge when they share no view and
    ``test`` accepts them. Returns (n,) each keypoint's root. Compiled: the merge loop runs
    over every scored pair of a window (10⁴–10⁵). Not cached: numba cannot cache a function
    taking another (~1 s to compile once per process and test; the node's warm-up takes it)."""
    parent = np.arange(n)
    # each root's members as a linked list: first, next, last, count
    first, nxt, last = np.arange(n), np.full(n, -1), np.arange(n)
    count = np.ones(n, np.int64)
    stamp = np.full(n_views, -1)  # stamp[v] == e: view v holds a member of the first track at pair e
    members = np.empty(n, np.int64)
    for e in range(rows.shape[0]):
        ra, rb = _root(parent, rows[e]), _root(parent, cols[e])
        if ra == rb:
            continue
        k, x = 0, first[ra]
        while x >= 0:
            stamp[view[x]] = e
            members[k] = x
            k += 1
            x = nxt[x]
        shared, x = False, first[rb]
        while x >= 0:
            if stamp[view[x]] == e:
                shared = True
                break
            members[k] = x
            k += 1
            x = nxt[x]
        if shared or not test(data, members[:k], count[ra], count[rb]):
            continue
        parent[rb] = ra
        nxt[last[ra]] = first[rb]
        last[ra] = last[rb]
        count[ra] += count[rb]
    roots = np.empty(n, np.int64)
    for a in range(n):
        roots[a] = _root(parent, a)
    return roots


@numba.njit(cache=True)
def _root(parent, a):
    root = a
    while parent[root] != root:
        root = parent[root]
    while parent[a] != root:  # path compression
        nxt = parent[a]
        parent[a] = root
        a = nxt
    return root


def relabel_tracks(labels: np.ndarray) -> np.ndarray:
    """Renumber groups 0..T-1 in order of first appearance; singletons and negatives become -1.

    Shapes: labels (N,) -> (N,) int64.
    """
    labels = np.asarray(labels, np.int64)
    out = np.full(labels.shape, -1, np.int64)
    valid = labels >= 0
    if not valid.any():
        return out
    uniq, first, inv, counts = np.unique(labels[valid], return_index=True, return_inverse=True,
                                         return_counts=True)
    multi = counts >= 2
    order = np.argsort(first[multi], kind="stable")
    ids = np.full(uniq.size, -1, np.int64)
    ids[np.flatnonzero(multi)[order]] = np.arange(order.size)
    out[valid] = ids[inv]
    return out


def track_members(track: np.ndarray):
    """The keypoints in tracks, track after track (ids ascending), each track's in keypoint
    order, and where each track starts among them (ids without members are skipped).

    Shapes: track (N,) int, -1 = none -> members (K,) int64, starts (T + 1,) int64 (T tracks).
    """
    track = np.asarray(track, np.int64)
    tracked = np.flatnonzero(track >= 0)
    members = tracked[np.argsort(track[tracked], kind="stable")]
    t = track[members]
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]]) if t.size else np.zeros(0, np.int64)
    return members, np.r_[starts, t.size]


def tracks_to_pairs(track: np.ndarray):
    """All unordered pairs (rows < cols) of keypoints sharing a track id >= 0."""
    members, starts = track_members(track)
    r_list, c_list = [], []
    for s, e in zip(starts[:-1], starts[1:]):
        a, b = np.triu_indices(e - s, 1)
        r_list.append(members[s + a])
        c_list.append(members[s + b])
    if not r_list:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(r_list), np.concatenate(c_list)


def is_cycle_consistent(track: np.ndarray, view_index: np.ndarray) -> bool:
    """True when no track holds two keypoints of one view (then A↔B, B↔C imply A↔C)."""
    track = np.asarray(track, np.int64)
    m = track >= 0
    keys = track[m] * (int(np.max(view_index)) + 1 if len(view_index) else 1) + np.asarray(view_index)[m]
    return keys.size == np.unique(keys).size


#: Connected components up to this size get a dense eigendecomposition; larger ones use Lanczos.
_DENSE_COMPONENT_MAX = 3000


def estimate_universe_size(adjacency: sp.spmatrix, view_sizes: np.ndarray, max_rank: int | None = None) -> int:
    """Estimate the number of distinct scene points d from the spectrum of A + I.

    For a cycle-consistent A + I = X Xᵀ (X the N×d keypoint-to-point assignment) the
    non-zero eigenvalues are the track lengths (>= 1; an isolated keypoint gives exactly 1) and
    all others are 0. Points never connect different connected components of the graph, so d is
    the sum over components: in a component C, d_C is taken at the largest gap
    λ_k − λ_{k+1} of its sorted eigenvalues (clipped at 0, λ_{n+1} = 0), searched from the
    largest number of keypoints C holds in one view (those must be different points) up to |C|.
    The total is clipped to [largest view size, max_rank].

    (The earlier rule — one largest gap over the whole spectrum — mixed the plateaus of
    different components: on the binary nearest-neighbour graphs of the 6-view Oxford problems
    it returned d ≈ 1200–1550, near N, which halved the spectral methods' recall; counting
    eigenvalues >= ~1 instead fails on dense noisy graphs, where dropped and wrong edges create
    eigenvalues near 1.)

    The spectrum is computed exactly per component, densely up to 3000 nodes; above that
    (e.g. one giant component of a k-NN graph) the top eigenvalues come from Lanczos, computed
    until they fall below 0.5, and the gap is searched among them.

    Args:
        adjacency: (N, N) symmetric, cross-view weights in [0, 1], zero diagonal
            (a diagonal, if present, is ignored); keypoints stored view after view.
        view_sizes: (V,) keypoints per view.
        max_rank: upper bound for d (default N).
    Returns:
        d with max(view_sizes) <= d <= max_rank.
    """
    n = adjacency.shape[0]
    sizes = np.asarray(view_sizes, np.int64)
    lo = int(np.max(sizes)) if len(sizes) else 0
    hi = n if max_rank is None else min(n, int(max_rank))
    if n == 0 or lo >= hi:
        return max(min(lo, hi), 0)
    a = sp.csr_matrix(adjacency, dtype=np.float64)
    a = ((a + a.T) * 0.5).tocsr()
    a.setdiag(0.0)
    a.eliminate_zeros()
    view = np.repeat(np.arange(len(sizes)), sizes) if sizes.sum() == n else np.zeros(n, np.int64)
    d = _points_per_component(a, view)
    return int(min(max(d, lo), hi))


def _points_per_component(a: sp.csr_matrix, view: np.ndarray) -> int:
    """Σ over connected components of the largest-gap rank of A + I (see estimate_universe_size)."""
    n_comp, labels = connected_components(a, directed=False)
    sizes = np.bincount(labels, minlength=n_comp)
    n_views = int(view.max()) + 1 if view.size else 1
    min_points = np.bincount(labels * n_views + view, minlength=n_comp * n_views).reshape(n_comp, n_views).max(axis=1)
    order = np.argsort(labels, kind="stable")
    starts = np.r_[0, np.cumsum(sizes)]
    total = int(np.sum(sizes == 1))  # an isolated keypoint is one point
    for s in np.unique(sizes[sizes > 1]):
        comps = np.flatnonzero(sizes == s)
        for chunk in np.array_split(comps, max(1, int(np.ceil(comps.size * s * s / 4e6)))):
            nodes = order[starts[chunk][:, None] + np.arange(s)[None, :]]
            flat = nodes.ravel()
            sub = a[flat][:, flat]
            if s <= _DENSE_COMPONENT_MAX:
                k = chunk.size
                coo = sub.tocoo()
                blocks = np.zeros((k, s, s))
                blocks[coo.row // s, coo.row % s, coo.col % s] = coo.data
                blocks[:, np.arange(s), np.arange(s)] += 1.0
                ev = np.linalg.eigvalsh(blocks)[:, ::-1]
            else:
                ev = _top_eigenvalues(sub + sp.identity(s, format="csr"), floor=0.5)[None, :]
            total += int(np.sum(_largest_gap_rank(ev, min_points[chunk])))
    return total


def _largest_gap_rank(ev: np.ndarray, min_rank: np.ndarray) -> np.ndarray:
    """Per row of descending eigenvalues (k, s): the k >= min_rank maximising λ_k − λ_{k+1} (λ_{s+1} = 0)."""
    ev = np.maximum(ev, 0.0)
    gaps = ev - np.concatenate([ev[:, 1:], np.zeros((ev.shape[0], 1))], axis=1)
    ranks = np.arange(1, ev.shape[1] + 1)
    gaps = np.where(ranks[None, :] >= np.minimum(min_rank, ev.shape[1])[:, None], gaps, -np.inf)
    return np.argmax(gaps, axis=1) + 1


def _top_eigenvalues(m: sp.csr_matrix, floor: float) -> np.ndarray:
    """Descending top eigenvalues of one large sparse component, by Lanczos with a growing k,
    until one falls below ``floor`` (or all but two are computed)."""
    size = m.shape[0]
    k = min(size - 2, 256)
    while True:
        vals = np.sort(spla.eigsh(m, k=k, which="LA", return_eigenvectors=False))[::-1]
        if vals[-1] < floor or k >= size - 2:
            return vals
        k = min(size - 2, 2 * k)
