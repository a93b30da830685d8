"""Near-duplicate keypoints: which of them a track takes.

Detectors report one corner several times: OpenCV's ORB detects on eight pyramid levels, and
58 % of its 500 keypoints in an Oxford image have another keypoint of the same image within
3 px (SIFT: 3 %). A track holds one keypoint per view, so which near-duplicate joins is decided
by the merge order — scores that are nearly equal — and the point can even split into two
tracks, x_a–y'_b and x'_a–y_b, each holding one of the duplicates of both views. Where every
view pair of a track is verified by a homography, the homographies predict each member's
*position* from the others, and the track can take the better-placed keypoint. After merging,
for a member m of track T in view b and a near-duplicate d of it (closer than
:data:`DUPLICATE_PX`), with P(x, T) the total transfer error of x against T's members in the
other views::

    d in no track:      replace m by d              if  P(d, T) < P(m, T)
    d in track T':      exchange m and d            if  P(d, T) + P(m, T') < P(m, T) + P(d, T')

each x within every homography's tolerance. Track sizes never change, so nothing the merge
joined is lost. An epipolar model predicts only a line, along which near-duplicates cannot be
ranked: tracks with a view pair verified by one are left as merged. (Ranking the pairs before
the merge instead — the better-placed partner merged first — was measured and not adopted: on the
ORB development windows of benchmarks/geometric_eval.py, 3-D scenes whose homographies only
approximate a plane, geometric precision 0.929 -> 0.922 with fewer consistent pairs, while the
Oxford ORB windows below gained more: F1 0.842.)

Measured, ``gcn:prefer_localised=false`` -> the default: the 16 Oxford ORB windows of
benchmarks/real_eval.py (exact labels, which mark the keypoint nearest the true position and
leave its near-duplicates unlabelled) F1 0.826 -> 0.833 (precision 0.944 -> 0.948), the 16 other
Oxford ORB windows (images 2-6) 0.619 -> 0.631, Oxford SIFT 0.967 unchanged; against the true
cameras (benchmarks/geometric_eval.py) ORB development windows 0.929 -> 0.931 geometric
precision, castle-P19 0.924 -> 0.928, SIFT development windows identical, castle-P19 two more
consistent pairs. ``nn-ransac:guided=true`` shares the rule: Oxford ORB 0.782 -> 0.804.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..view_pairs import by_view_pair
from .verify import residuals

__all__ = ["DUPLICATE_PX", "better_placed_members"]

#: Two keypoints of one view closer than this are near-duplicates: the homography's inlier
#: tolerance (:data:`.verify.RANSAC_PX`), within which the model accepts either as the partner.
DUPLICATE_PX = 3.0


def better_placed_members(geometry, track: np.ndarray, duplicate_px: float = DUPLICATE_PX) -> np.ndarray:
    """``track`` with members replaced by, or exchanged with, the near-duplicates the
    homographies place better (module docstring). A track changes at most one member, the
    largest gain first.

    Args:
        geometry: the window's :class:`.consistency.WindowGeometry`.
        track: (N,) int64 track ids (-1: in no track), one keypoint per view and track.
        duplicate_px: near-duplicates are closer than this (pixels).

    Returns:
        (N,) int64: the same track ids, over the same number of keypoints each.
    """
    track = np.array(track, np.int64, copy=True)
    planar, tolerance = _homographies(geometry)
    if not planar.any() or not (track >= 0).any():
        return track
    member, rival = _near_duplicates(geometry, track, planar.any(axis=1), duplicate_px)
    if member.size == 0:
        return track
    t_member, t_rival = track[member], track[rival]
    free = t_rival < 0
    placement = _Placement(geometry, track, planar, tolerance)
    other = np.where(free, t_member, t_rival)
    # P(m, T), P(d, T), P(d, T'), P(m, T') in one pass
    p_mt, p_dt, p_do, p_mo = np.split(placement(np.r_[member, rival, rival, member],
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


def _homographies(geometry):
    """(V, V) whether a view pair is verified by a homography, and that homography's tolerance."""
    V = geometry.problem.n_views
    planar, tolerance = np.zeros((V, V), bool), np.zeros((V, V))
    for (a, b), model in geometry.models.items():
        planar[a, b] = planar[b, a] = model.planar
        tolerance[a, b] = tolerance[b, a] = model.px
    return planar, tolerance


class _Placement:
    """P(x, T) of module docstring for many (x, T) at once: +inf where T has a member in another
    view whose view pair with x's is not verified by a homography or whose homography x
    disagrees with."""

    def __init__(self, geometry, track, planar, tolerance):
        self.geometry, self.track, self.planar, self.tolerance = geometry, track, planar, tolerance
        tracked = np.flatnonzero(track >= 0)
        self.by_track = tracked[np.argsort(track[tracked], kind="stable")]
        self.size = np.bincount(track[tracked], minlength=track.max() + 1)
        self.first = np.r_[0, np.cumsum(self.size)[:-1]]

    def __call__(self, x: np.ndarray, t: np.ndarray) -> np.ndarray:
        view, kp = self.geometry.view_index, self.geometry.keypoints
        n = self.size[t]
        k = np.repeat(np.arange(x.size), n)
        other = self.by_track[self.first[t][k] + np.arange(k.size) - np.repeat(np.cumsum(n) - n, n)]
        apart = view[other] != view[x[k]]
        k, other, xk = k[apart], other[apart], x[k[apart]]
        error = np.full(k.size, np.inf)
        lo = view[xk] < view[other]
        a_kp, b_kp = np.where(lo, xk, other), np.where(lo, other, xk)
        for (a, b), m in by_view_pair(view[a_kp], view[b_kp]).items():
            model = self.geometry.models.get((a, b))
            if model is not None and model.planar:
                error[m] = residuals(model.selected(), kp[a_kp[m]], kp[b_kp[m]])[0]
        error[~(error <= self.tolerance[view[xk], view[other]])] = np.inf
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
