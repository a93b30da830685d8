"""Pairs their neighbours do not follow: neighbourhood consensus between two views.

Two views of one surface keep its layout: the keypoints next to a point in one view are,
mostly, next to its image in the other, whatever the depth and the camera motion (locality
preserving matching, Ma et al., IJCV 2019). A match shifted to a repetition of its point (the
next window of a facade, the next tile along a roof edge) keeps the epipolar geometry to within
pixels — no two-view model can refuse it (:mod:`.ambiguity` refuses the ones its descriptors
show as ambiguous) — but lands among the neighbours of another point. For a pair (x_a, x_b) of a
view pair, with the *reference* pairs of that view pair (the confident ones, which tracks are
merged from)::

    shared(x_a, x_b) = | N_k(x_a) ∩ N_k(x_b) |

where N_k(x_a) are the k reference pairs whose keypoint in view a lies nearest x_a, N_k(x_b)
those whose keypoint in view b lies nearest x_b (the pair itself left out). Right pairs share
most of their neighbours; a pair that shares almost none is far more often wrong (pairs of gcn's
tracks on the development scenes, k = 8: 36 % right with none shared, 98 % with all 8).

Only near-copies are judged (cosine at least :data:`.ambiguity.MIN_JUDGED_COSINE`): a
repetition looks like its point. Where descriptors are weak and the points float in a volume
rather than lie on surfaces (the generated scenes), right pairs keep fewer neighbours: judging
every pair there cost F1 0.003-0.006 (rome16k, 3 and 4 views); judging near-copies changes
nothing there.

k and the minimum were chosen on the development scenes of benchmarks/geometric_eval.py by a
rule fixed before: the highest geometric precision among settings that keep at least the
consistent pairs of the rule off (measured judging every pair; precision / consistent pairs): off
0.962 / 33 601; k = 8, at least 1: 0.964 / 33 607; **k = 8, at least 2: 0.965 / 33 610**;
k = 12, at least 3: 0.964 / 33 619; k = 8, at least 3: 0.967 / 33 571; k = 6, at least 2:
0.967 / 33 553; k = 8, at least 4: 0.968 / 33 524. The held-out castle-P19 was measured with
the choice, not tuned on: 0.897 -> 0.910 with more consistent pairs (9 770 -> 9 778); judging
near-copies only (the default): dev 0.965 / 33 619, castle 0.909 / 9 784.
Pose-free and model-free; deterministic (a k-d tree's neighbours).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

from ..view_pairs import by_view_pair, in_view_order

__all__ = ["NEIGHBOURS", "MIN_SHARED", "shared_neighbours", "followed_pairs", "check_neighbourhood"]

#: neighbours compared per view (k)
NEIGHBOURS = 8
#: a pair sharing fewer of them is dropped (module docstring)
MIN_SHARED = 2


def check_neighbourhood(k: int, min_shared: int) -> None:
    """Refuse solver settings outside 0 <= min_shared <= k (k = 0: the rule is off, any min_shared >= 0)."""
    if k < 0 or min_shared < 0 or (k > 0 and min_shared > k):
        raise ValueError(f"neighbourhood: need k >= 0 and 0 <= min_shared <= k, got k={k}, min_shared={min_shared}")


def _nearest_others(tree: cKDTree, points: np.ndarray, self_index: np.ndarray, k: int) -> np.ndarray:
    """The k reference points nearest each of ``points``, leaving out its own reference index
    (``self_index``; -1: not a reference point).

    Shapes: points (Q, 2), self_index (Q,) -> (Q, k) int64.
    """
    _, near = tree.query(points, k + 1)
    near = np.asarray(near, np.int64).reshape(points.shape[0], k + 1)
    own = near == self_index[:, None]
    # own index (if found) moved last, the others' order kept; then the first k
    order = np.argsort(own, axis=1, kind="stable")
    return np.take_along_axis(near, order, axis=1)[:, :k]


def shared_neighbours(xa: np.ndarray, xb: np.ndarray, ref: np.ndarray, k: int = NEIGHBOURS,
                      judged: Optional[np.ndarray] = None) -> np.ndarray:
    """How many of its k nearest reference pairs each pair has in both views (module docstring).

    Args:
        xa, xb: the pairs' keypoints in view a and in view b (pixels).
        ref: which pairs are reference pairs (their neighbourhoods are counted).
        k: neighbours per view.
        judged: the pairs whose count is wanted (default: all); the others get ``k`` uncounted
            (a window's near-copies are few, its reference pairs hundreds).

    Returns:
        (M,) int64: shared neighbours, ``k`` for every pair when there are at most k reference
        pairs (too few to tell a neighbourhood from the whole view).

    Shapes: xa, xb (M, 2), ref (M,) bool, judged (M,) bool.
    """
    m = xa.shape[0]
    ref_at = np.flatnonzero(ref)
    shared = np.full(m, k, np.int64)
    if ref_at.size <= k or k == 0:
        return shared
    wanted = np.arange(m) if judged is None else np.flatnonzero(judged)
    self_index = np.full(m, -1, np.int64)
    self_index[ref_at] = np.arange(ref_at.size)
    near_a = _nearest_others(cKDTree(xa[ref_at]), xa[wanted], self_index[wanted], k)
    near_b = _nearest_others(cKDTree(xb[ref_at]), xb[wanted], self_index[wanted], k)
    shared[wanted] = (near_a[:, :, None] == near_b[:, None, :]).any(axis=2).sum(axis=1)
    return shared


def followed_pairs(keypoints: np.ndarray, view_index: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                   judged: np.ndarray, ref: np.ndarray, k: int = NEIGHBOURS, min_shared: int = MIN_SHARED) -> np.ndarray:
    """Which pairs keep their neighbours: per view pair, each ``judged`` pair shares at least
    ``min_shared`` of its k nearest ``ref`` pairs of that view pair in both views
    (:func:`shared_neighbours`); pairs not judged are left as they are (True).

    Shapes: keypoints (N, 2); view_index (N,); rows, cols, judged, ref (M,) -> (M,) bool.
    """
    out = np.ones(np.shape(rows)[0], bool)
    if k == 0 or min_shared == 0 or not judged.any():
        return out
    lo, hi, va, vb = in_view_order(view_index, rows, cols)
    counted = np.flatnonzero(judged | ref)
    for at in by_view_pair(va[counted], vb[counted]).values():
        at = counted[at]
        if not judged[at].any():
            continue
        shared = shared_neighbours(keypoints[lo[at]].astype(np.float64), keypoints[hi[at]].astype(np.float64),
                                   ref[at], k, judged[at])
        out[at] = ~judged[at] | (shared >= min_shared)
    return out
