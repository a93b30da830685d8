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

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

__all__ = ["greedy_tracks", "relabel_tracks", "estimate_universe_size", "tracks_to_pairs",
           "is_cycle_consistent"]


def greedy_tracks(n_nodes: int, view_index: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                  scores: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Merge keypoints into tracks from the best-scored pair down, never two of one view.

    Args:
        n_nodes: N.
        view_index: (N,) view of each keypoint.
        rows, cols, scores: (M,) candidate pairs and their scores.
        threshold: pairs scoring below it are never merged.

    Returns:
        (N,) int64 track ids 0..T-1 for keypoints in a track of >= 2 keypoints, -1 otherwise.
    """
    view_index = np.asarray(view_index, np.int64)
    keep = np.flatnonzero(np.asarray(scores) >= threshold)
    order = keep[np.argsort(-np.asarray(scores)[keep], kind="stable")]
    # Plain Python lists: scalar access in this loop is several times faster than on numpy arrays.
    parent = list(range(n_nodes))
    # Track view sets as Python ints (bit v = view v): any number of views, O(1) disjointness test.
    views = [1 << int(v) for v in view_index]
    rows, cols = np.asarray(rows)[order].tolist(), np.asarray(cols)[order].tolist()

    def find(a: int) -> int:
        root = a
        while parent[root] != root:
            root = parent[root]
        while parent[a] != root:  # path compression
            parent[a], a = root, parent[a]
        return root

    for a, b in zip(rows, cols):
        ra, rb = find(a), find(b)
        if ra == rb or views[ra] & views[rb]:
            continue
        parent[rb] = ra
        views[ra] |= views[rb]
    roots = np.array([find(a) for a in range(n_nodes)], dtype=np.int64)
    return relabel_tracks(roots)


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


def tracks_to_pairs(track: np.ndarray):
    """All unordered pairs (rows < cols) of keypoints sharing a track id >= 0."""
    track = np.asarray(track, np.int64)
    idx = np.flatnonzero(track >= 0)
    order = idx[np.argsort(track[idx], kind="stable")]
    t = track[order]
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]])
    ends = np.r_[starts[1:], t.size]
    r_list, c_list = [], []
    for s, e in zip(starts, ends):
        members = np.sort(order[s:e])
        a, b = np.triu_indices(members.size, 1)
        r_list.append(members[a])
        c_list.append(members[b])
    if not r_list:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(r_list), np.concatenate(c_list)


def is_cycle_consistent(track: np.ndarray, view_index: np.ndarray) -> bool:
    """True when no track holds two keypoints of one view (then A↔B, B↔C imply A↔C)."""
    track = np.asarray(track, np.int64)
    m = track >= 0
    keys = track[m] * (int(np.max(view_index)) + 1 if len(view_index) else 1) + np.asarray(view_index)[m]
    return keys.size == np.unique(keys).size


#: Eigenvalues of A + I at or above this level count as scene points (see estimate_universe_size).
UNIVERSE_EIGENVALUE_LEVEL = 0.9
#: Connected components up to this size get a dense eigendecomposition; larger ones use Lanczos.
_DENSE_COMPONENT_MAX = 3000


def estimate_universe_size(adjacency: sp.spmatrix, view_sizes: np.ndarray, max_rank: int | None = None) -> int:
    """Estimate the number of distinct scene points d from the spectrum of A + I.

    For a cycle-consistent A + I = X Xᵀ (X the N×d keypoint-to-point assignment) the
    non-zero eigenvalues are the track lengths (>= 1: an isolated keypoint gives exactly 1)
    and all others are 0, so d is the number of eigenvalues >= 1. Wrong and missing edges
    spread the spectrum; directions clearly below 1 come from disagreeing edges (a path
    a–b–c missing a–c has 1 ± √2 and 1), so d counts the eigenvalues
    >= ``UNIVERSE_EIGENVALUE_LEVEL`` (0.9), clipped to [largest view size, max_rank]
    (every keypoint of a view is a different point).

    (The earlier rule — the largest gap between consecutive eigenvalues — jumped between
    the plateaus at 3, 2, 1 and the near-zero tail: on the 6-view Oxford problems it returned
    d ≈ 1200–1550 where ~1000–1150 eigenvalues are >= 1, halving the spectral methods' recall.)

    The spectrum is computed exactly, one connected component of the graph at a time (the
    nearest-neighbour graphs the synchronisation methods get fall apart into thousands of
    small components), densely up to 3000 nodes per component and with Lanczos above.

    Args:
        adjacency: (N, N) symmetric, cross-view weights in [0, 1], zero diagonal
            (a diagonal, if present, is ignored).
        view_sizes: (V,) keypoints per view.
        max_rank: upper bound for d (default N).
    Returns:
        d with max(view_sizes) <= d <= max_rank.
    """
    n = adjacency.shape[0]
    lo = int(np.max(view_sizes)) if len(view_sizes) else 0
    hi = n if max_rank is None else min(n, int(max_rank))
    if n == 0 or lo >= hi:
        return max(min(lo, hi), 0)
    a = sp.csr_matrix(adjacency, dtype=np.float64)
    a = ((a + a.T) * 0.5).tocsr()
    a.setdiag(0.0)
    a.eliminate_zeros()
    count = _count_eigenvalues_at_least(a, UNIVERSE_EIGENVALUE_LEVEL, cap=hi)
    return int(min(max(count, lo), hi))


def _count_eigenvalues_at_least(a: sp.csr_matrix, level: float, cap: int) -> int:
    """Number of eigenvalues of A + I that are >= level, per connected component (stops counting at cap)."""
    n_comp, labels = connected_components(a, directed=False)
    sizes = np.bincount(labels, minlength=n_comp)
    order = np.argsort(labels, kind="stable")
    starts = np.r_[0, np.cumsum(sizes)]
    count = 0
    for s in np.unique(sizes):
        comps = np.flatnonzero(sizes == s)
        if s == 1:  # isolated keypoint: eigenvalue exactly 1
            count += comps.size if level <= 1.0 else 0
            continue
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
                count += int((np.linalg.eigvalsh(blocks) >= level).sum())
            else:
                count += _count_large(sub + sp.identity(s, format="csr"), level, cap - count)
        if count >= cap:
            return count
    return count


def _count_large(m: sp.csr_matrix, level: float, cap: int) -> int:
    """Eigenvalues >= level of one large sparse component, by Lanczos with a growing k."""
    size = m.shape[0]
    k = min(size - 2, max(64, min(cap, size // 4)))
    while True:
        vals = spla.eigsh(m, k=k, which="LA", return_eigenvectors=False)
        c = int((vals >= level).sum())
        if c < k or k >= size - 2 or c >= cap:
            return c
        k = min(size - 2, 2 * k)
