"""Keypoints a track's members place point to point: they join at the point-to-point threshold.

The precision-first threshold guards against what an epipolar check lets through: a match
shifted along its epipolar line (a repetition, or a point the other view does not see that
happens to lie on the line) agrees with its view pair's model. A keypoint that a track's members
*place* is checked point to point instead: two members in views whose epipolar lines towards its
view cross at :data:`.support.MIN_CROSSING_DEG` or more (the lines cross at one point), or one
member whose view pair's model is a homography. A pair scored at least the window's
point-to-point threshold (the solver's ``planar_threshold``, as for a window that sees one plane)
that adds such a keypoint to a track is merged when the keypoint agrees with every member
(:class:`.consistency.TrackCheck`). The members that place are those merged at the threshold: a
keypoint that joined below it places nothing, so weak evidence does not chain.

Measured before the choice on generated windows of their own (seeds [11, 1000..1019]) and the
3-D development windows of benchmarks/geometric_eval.py (SIFT, stored thresholds 0.5 / 0.2): the
candidates of generated 3-view windows scored 0.4-0.5 are 66 % right on rome16k, 26 % on partial
(the head cannot tell rome16k's ambiguous descriptors from a partial view's unseen points), and were
left out of tracks; joining the placed ones gave rome16k F1 0.935 -> 0.954, partial 0.876 -> 0.871, dev precision
0.963 -> 0.960 (worst separation 0.888 -> 0.877). The rule's lower bound 0.4 or 0.3 instead of
the point-to-point threshold gave rome16k 0.950 / 0.952, partial 0.879 / 0.876; the members'
own tolerance instead of the chain tolerance (a stricter placement) 0.944, partial 0.877. Placed by
the members merged at the threshold only (the compiled rule here): 0.953, partial 0.870.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numba
import numpy as np

from ..rounding import MergeTest, track_members
from .support import MIN_CROSSING_DEG

if TYPE_CHECKING:  # consistency imports this module
    from .consistency import WindowGeometry

__all__ = ["placed_members"]


def placed_members(geometry: "WindowGeometry", track: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                   scores: np.ndarray, low: float, high: float, check: MergeTest) -> np.ndarray:
    """Tracks grown by the keypoints their members place (module docstring), best pair first.

    Args:
        geometry: the window's models of the view pairs' own descriptor seeds, without chained
            ones (:meth:`.consistency.WindowGeometry.with_chained_models`: fitted on what the tracks
            chained, they would vouch for the tracks' own growth).
        track: (N,) track of every keypoint (-1: none), merged from the pairs scoring >= ``high``.
        rows, cols, scores: (M,) the kept pairs with their scores; those scoring in [low, high)
            between a keypoint of a track and one of none are tried.
        low, high: the point-to-point threshold and the threshold.
        check: the track check of ``geometry`` (:class:`.consistency.TrackCheck`), asked with the
            track's members and the placed keypoint.

    Returns:
        (N,) int64: ``track`` with the placed keypoints added (ids unchanged).
    """
    track = np.array(track, np.int64)
    rows, cols, scores = np.asarray(rows, np.int64), np.asarray(cols, np.int64), np.asarray(scores)
    band = np.flatnonzero((scores >= low) & (scores < high))
    in_row, in_col = track[rows[band]] >= 0, track[cols[band]] >= 0
    band, from_row = band[in_row != in_col], in_row[in_row != in_col]
    if not band.size:
        return track
    x = np.where(from_row, rows[band], cols[band])
    y = np.where(from_row, cols[band], rows[band])
    members, starts = track_members(track)
    view = np.asarray(geometry.view_index, np.int64)
    places = _places(members, starts, int(np.diff(starts).max()), view, np.asarray(geometry.keypoints, np.float64),
                     *_directed_models(geometry), math.sin(math.radians(MIN_CROSSING_DEG)))
    t, v = track[x], view[y]
    placed = places[t, v]
    order = np.flatnonzero(placed)[np.argsort(-scores[band[placed]], kind="stable")]
    groups = {}
    for i in order.tolist():
        ti, vi, yi = int(t[i]), int(v[i]), int(y[i])
        if track[yi] >= 0 or not places[ti, vi]:  # placed meanwhile, or the track took view v
            continue
        group = groups.get(ti)
        if group is None:
            group = groups[ti] = members[starts[ti]:starts[ti + 1]].tolist()
        if check.test(check.data, np.array(group + [yi], np.int64), len(group), 1):
            track[yi] = ti
            group.append(yi)
            places[ti, vi] = False
    return track


def _directed_models(geometry: "WindowGeometry"):
    """Per ordered view pair (a, b) whether its model places: verified by a model of its own seeds
    (:attr:`.consistency.WindowGeometry.checkable` views), whether that model is a homography
    (which places a point), and its F oriented a -> b (F x_a is x_a's line in view b).

    Returns: (V, V) bool, (V, V) bool, (V, V, 3, 3) float64."""
    V = geometry.verified.shape[0]
    placing = geometry.verified & geometry.checkable
    planar = np.zeros((V, V), bool)
    F = np.zeros((V, V, 3, 3))
    for (a, b), model in geometry.models.items():
        planar[a, b] = planar[b, a] = model.inlier_rule[0]
        if model.F is not None:
            F[a, b], F[b, a] = model.F, model.F.T
    return placing, planar, F


@numba.njit(cache=True, nogil=True)
def _places(members, starts, longest, view, kp, placing, planar, F, min_sine):
    """(T, V): whether track t's members place a point in view v — none of them is in v, and one
    has a homography to v or two have epipolar lines in v that cross at an angle whose sine is at
    least ``min_sine``. Compiled: a window has hundreds of tracks.

    Shapes: members (K,), starts (T + 1,) (:func:`gcn_match_ros.rounding.track_members`; ``longest``
    the most members of a track); view (N,); kp (N, 2); placing, planar (V, V); F (V, V, 3, 3)
    -> (T, V) bool."""
    T, V = starts.shape[0] - 1, placing.shape[0]
    out = np.zeros((T, V), np.bool_)
    normals = np.empty((longest, 2))  # unit normals of the lines so far
    for t in range(T):
        for v in range(V):
            held, point, n = False, False, 0
            for k in range(starts[t], starts[t + 1]):
                a = view[members[k]]
                if a == v:
                    held = True
                    break
                if not placing[a, v]:
                    continue
                if planar[a, v]:
                    point = True
                    continue
                x, y = kp[members[k], 0], kp[members[k], 1]
                l0 = F[a, v, 0, 0] * x + F[a, v, 0, 1] * y + F[a, v, 0, 2]
                l1 = F[a, v, 1, 0] * x + F[a, v, 1, 1] * y + F[a, v, 1, 2]
                norm = math.sqrt(l0 * l0 + l1 * l1)
                if norm <= 0.0:
                    continue
                l0, l1 = l0 / norm, l1 / norm
                for j in range(n):
                    if abs(normals[j, 0] * l1 - normals[j, 1] * l0) >= min_sine:
                        point = True
                normals[n, 0], normals[n, 1] = l0, l1
                n += 1
            out[t, v] = point and not held
    return out
