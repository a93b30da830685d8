"""Near-duplicate keypoints: which of them a track takes.

Detectors report one corner several times: OpenCV's ORB detects on eight pyramid levels, and
58 % of its 500 keypoints in an Oxford image have another keypoint of the same image within
3 px (SIFT: 3 %). A track holds one keypoint per view, so which near-duplicate joins is decided
by the merge order — scores that are nearly equal — and the point can even split into two
tracks, x_a–y'_b and x'_a–y_b, each holding one of the duplicates of both views. In a window
that sees one plane (every view pair of at least three views verified by a homography,
:attr:`.consistency.WindowGeometry.one_plane`) the homographies predict each keypoint's
*position*, and the tracks take the better-placed keypoints (e: a homography's symmetric
transfer error):

1. Before the merge: of a keypoint's candidate partners in one view that are near-duplicates
   (closer than :data:`DUPLICATE_PX`), the better-placed one is merged first
   (:func:`merge_order`); the other keeps its place behind it and still joins where the better
   one cannot.
2. After the merge: a member m of track T in view b and a near-duplicate d of it, with P(x, T)
   the total transfer error of x against T's members in the other views
   (:func:`better_placed_members`)::

       d in no track:      replace m by d              if  P(d, T) < P(m, T)
       d in track T':      exchange m and d            if  P(d, T) + P(m, T') < P(m, T) + P(d, T')

   each x within every homography's tolerance. Track sizes never change.

Elsewhere the homography of a view pair only approximates a 3-D scene, and ranking by it hurt,
measured: both steps in every window (on tracks whose view pairs are all homographies) cost the
ORB development windows of benchmarks/geometric_eval.py geometric precision (step 1: 0.929 ->
0.922) and the generated rigs of benchmarks/landmark_eval.py their landmark ids (step 2: 4
cameras, fragmentation 1.10 -> 1.17 per point), while on castle-P19's ORB windows step 2 helped
(0.924 -> 0.928). Measured as adopted: docs/results.md, "One-plane windows and near-duplicate keypoints".
"""
from __future__ import annotations

import numba
import numpy as np
from scipy.spatial import cKDTree

from ..view_pairs import by_view_pair
from .verify import residuals

__all__ = ["DUPLICATE_PX", "KEY_STEP", "merge_order", "better_placed_members"]

#: Two keypoints of one view closer than this are near-duplicates: the homography's inlier
#: tolerance (:data:`.verify.RANSAC_PX`), within which the model accepts either as the partner.
DUPLICATE_PX = 3.0


def better_placed_members(geometry, track: np.ndarray, duplicate_px: float = DUPLICATE_PX) -> np.ndarray:
    """``track`` with members replaced by, or exchanged with, the near-duplicates the
    homographies place better (module docstring, step 2). A track changes at most one member,
    the largest gain first.

    Args:
        geometry: the window's :class:`.consistency.WindowGeometry`.
        track: (N,) int64 track ids (-1: in no track), one keypoint per view and track.
        duplicate_px: near-duplicates are closer than this (pixels).

    Returns:
        (N,) int64: the same track ids, over the same number of keypoints each.
    """
    track = np.array(track, np.int64, copy=True)
    if not geometry.planar.any() or not (track >= 0).any():
        return track
    member, rival = _near_duplicates(geometry, track, geometry.planar.any(axis=1), duplicate_px)
    if member.size == 0:
        return track
    t_member, t_rival = track[member], track[rival]
    free = t_rival < 0
    other = np.where(free, t_member, t_rival)
    # P(m, T), P(d, T), P(d, T'), P(m, T') in one pass
    p_mt, p_dt, p_do, p_mo = np.split(_placements(geometry, track, np.r_[member, rival, rival, member],
                                                  np.r_[t_member, t_member, other, other]), 4)
    with np.errstate(invalid="ignore"):  # inf - inf: neither placed, no gain (nan)
        gain = np.where(free, p_mt - p_dt, p_mt - p_dt + p_do - p_mo)
    usable = np.isfinite(gain) & (gain > 0)
    changed = np.zeros(track.max() + 1, bool)
    moved = np.zeros(track.shape[0], bool)
    for i in np.flatnonzero(usable)[np.argsort(-gain[usable], kind="stable")]:
        m, d, t, u = member[i], rival[i], t_member[i], t_rival[i]
        if changed[t] or moved[m] or moved[d] or (u >= 0 and changed[u]):
            continue
        track[d], track[m] = t, u
        moved[m] = moved[d] = changed[t] = True
        if u >= 0:
            changed[u] = True
    return track


def _homography_errors(geometry, lo: np.ndarray, hi: np.ndarray):
    """Each pair's symmetric transfer error under its view pair's homography, and the error that
    homography accepts (:attr:`.verify.PairModel.px`); inf and 0 where the view pair is not
    verified by a homography.

    Shapes: lo, hi (M,) keypoints, lo's view below hi's -> (M,), (M,) float64.
    """
    view, kp = geometry.view_index, geometry.keypoints
    error, tolerance = np.full(lo.shape[0], np.inf), np.zeros(lo.shape[0])
    for (a, b), m in by_view_pair(view[lo], view[hi]).items():
        model = geometry.models.get((a, b))
        if model is not None and model.planar:
            error[m] = residuals(model.selected(), kp[lo[m]], kp[hi[m]])[0]
            tolerance[m] = model.px
    return error, tolerance


def _placements(geometry, track: np.ndarray, x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """P(x, T) of the module docstring for many (x, T) at once: +inf where T has a member in
    another view whose view pair with x's is not verified by a homography or whose homography x
    disagrees with.

    Shapes: track (N,); x (Q,) keypoints, t (Q,) track ids -> (Q,) float64.
    """
    view = geometry.view_index
    tracked = np.flatnonzero(track >= 0)
    by_track = tracked[np.argsort(track[tracked], kind="stable")]
    size = np.bincount(track[tracked], minlength=track.max() + 1)
    first = np.r_[0, np.cumsum(size)[:-1]]
    # every (x, member of T)
    n = size[t]
    k = np.repeat(np.arange(x.size), n)
    other = by_track[first[t][k] + np.arange(k.size) - np.repeat(np.cumsum(n) - n, n)]
    apart = view[other] != view[x[k]]
    k, other = k[apart], other[apart]
    lo, hi, _, _ = geometry.in_view_order(x[k], other)
    error, tolerance = _homography_errors(geometry, lo, hi)
    error[~(error <= tolerance)] = np.inf
    return np.bincount(k, weights=error, minlength=x.size)


def _near_duplicates(geometry, track: np.ndarray, views: np.ndarray, duplicate_px: float):
    """(member, rival) pairs: a keypoint in a track and a near-duplicate of it that is in no
    track or in another one, in the views flagged in ``views`` (each pair of two tracked
    keypoints once). Shapes: -> (P,), (P,) int64."""
    view, kp = geometry.view_index, geometry.keypoints
    listed = np.flatnonzero(views[view])
    if listed.size < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # one tree for every view: each view's keypoints moved far from the others'
    apart = np.abs(kp[listed]).max() * 2 + 4 * duplicate_px + 1
    spread = kp[listed] + np.c_[view[listed] * apart, np.zeros(listed.size)]
    close = cKDTree(spread).query_pairs(duplicate_px, output_type="ndarray")
    i, j = listed[close[:, 0]], listed[close[:, 1]]
    near = (np.sum((kp[i] - kp[j]) ** 2, axis=1) < duplicate_px ** 2) & (track[i] != track[j])
    i, j = i[near], j[near]
    flip = track[i] < 0  # the tracked one first
    return np.where(flip, j, i), np.where(flip, i, j)


def merge_order(geometry, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray, candidates: np.ndarray,
                duplicate_px: float = DUPLICATE_PX) -> np.ndarray:
    """The keys greedy merging takes the pairs in (descending): the scores, each pair of a
    homography view pair raised just above the competing pairs whose partner is a near-duplicate
    of its own and placed worse (module docstring, step 1). The worse pair keeps its place behind
    it, so it still joins where the better one cannot.

    Args:
        geometry: the window's :class:`.consistency.WindowGeometry`.
        rows, cols, scores: (M,) pairs of keypoints of different views and their scores.
        candidates: (M,) bool, the pairs that may be merged (only these compete).
        duplicate_px: near-duplicates are closer than this (pixels).

    Returns:
        (M,) float64 keys; equal to ``scores`` where no pair competes.
    """
    keys = np.asarray(scores, np.float64).copy()
    rows, cols, _, _ = geometry.in_view_order(rows, cols)
    listed = np.flatnonzero(candidates)
    error = np.full(rows.shape[0], np.inf)
    error[listed] = _homography_errors(geometry, rows[listed], cols[listed])[0]
    pairs = np.flatnonzero(np.isfinite(error))
    if pairs.size < 2:
        return keys
    for anchor, partner in ((rows, cols), (cols, rows)):
        # a keypoint's competing partners in one view are consecutive, the worst placed first
        order = pairs[np.lexsort((-error[pairs], geometry.view_index[partner[pairs]], anchor[pairs]))]
        _raise_better_placed(anchor[order], geometry.view_index[partner[order]], partner[order], order,
                             geometry.keypoints, float(duplicate_px), keys)
    return keys


#: How far above a worse-placed competitor a pair's key is raised: below any score difference
#: that matters, above the rounding of scores in [0, 1].
KEY_STEP = 1e-9


@numba.njit(cache=True)
def _raise_better_placed(anchor, partner_view, partner, pair, keypoints, duplicate_px, keys):
    """Over runs of equal (anchor, partner view), worst placed first: each pair's key is raised
    above the keys of the worse-placed near-duplicate partners before it. Runs hold a handful
    of pairs."""
    n = anchor.shape[0]
    start = 0
    limit = duplicate_px * duplicate_px
    while start < n:
        end = start + 1
        while end < n and anchor[end] == anchor[start] and partner_view[end] == partner_view[start]:
            end += 1
        for w in range(start + 1, end):
            for u in range(start, w):
                dx = keypoints[partner[u], 0] - keypoints[partner[w], 0]
                dy = keypoints[partner[u], 1] - keypoints[partner[w], 1]
                if dx * dx + dy * dy < limit and keys[pair[w]] <= keys[pair[u]]:
                    keys[pair[w]] = keys[pair[u]] + KEY_STEP
        start = end
