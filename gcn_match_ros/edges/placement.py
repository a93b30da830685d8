"""Keypoints a track's members place point to point: they join at the point-to-point threshold.

The precision-first threshold guards against what an epipolar check lets through: a match
shifted along its epipolar line (a repetition, or a point the other view does not see that
happens to lie on the line) agrees with its view pair's model. A keypoint that a track's members
*place* is checked point to point instead: two members in views whose epipolar lines towards its
view cross at :data:`.support.MIN_CROSSING_DEG` or more (the lines cross at one point), or one
member whose view pair's model is a homography. A pair scored at least the window's
point-to-point threshold (the solver's ``planar_threshold``, as for a window that sees one plane)
that adds such a keypoint to a track of two or more is merged when the keypoint agrees with every
member (:class:`.consistency.TrackCheck`).

Measured before the choice on generated windows of their own (seeds [11, 1000..1019]) and the
3-D development windows of benchmarks/geometric_eval.py (SIFT, stored thresholds 0.5 / 0.2): the
candidates of generated 3-view windows scored 0.4-0.5 are 66 % right on rome16k, 26 % on partial
(the head cannot tell rome16k's ambiguous descriptors from a partial view's unseen points), and were
left out of tracks; joining the placed ones gave rome16k F1 0.935 -> 0.954, partial 0.876 -> 0.871, dev precision
0.963 -> 0.960 (worst separation 0.888 -> 0.877). The rule's lower bound 0.4 or 0.3 instead of
the point-to-point threshold gave rome16k 0.950 / 0.952, partial 0.879 / 0.876; the members'
own tolerance instead of the chain tolerance (a stricter placement) 0.944, partial 0.877.
"""
from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, Dict, List

import numpy as np

from ..rounding import MergeTest, track_members
from .support import lines_cross, placed_in

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
            with one keypoint in a track and the other in none, when their turn comes, are tried.
        low, high: the point-to-point threshold and the threshold.
        check: the track check of ``geometry`` (:class:`.consistency.TrackCheck`), asked with the
            track's members and the placed keypoint.

    Returns:
        (N,) int64: ``track`` with the placed keypoints added (ids unchanged).
    """
    track = np.array(track, np.int64)
    rows, cols, scores = np.asarray(rows, np.int64), np.asarray(cols, np.int64), np.asarray(scores)
    band = np.flatnonzero((scores >= low) & (scores < high))
    if not band.size or (track < 0).all():
        return track
    members, starts = track_members(track)
    tracks: Dict[int, List[int]] = {int(track[members[s]]): members[s:e].tolist()
                                    for s, e in zip(starts[:-1], starts[1:])}
    view = geometry.view_index.tolist()
    placing = geometry.verified & geometry.checkable
    transfers: dict = {}
    places: Dict[tuple, bool] = {}  # (track, its size, view): whether its members place a point there
    for e in band[np.argsort(-scores[band], kind="stable")].tolist():
        x, y = (int(rows[e]), int(cols[e])) if track[rows[e]] >= 0 else (int(cols[e]), int(rows[e]))
        if track[x] < 0 or track[y] >= 0:  # a keypoint placed earlier can place its partners
            continue
        t, v = int(track[x]), view[y]
        group = tracks[t]
        key = (t, len(group), v)
        if key not in places:
            places[key] = all(view[m] != v for m in group) and _placed(geometry, transfers, placing, group, v)
        if places[key] and check.test(check.data, np.array(group + [y], np.int64), len(group), 1):
            track[y] = t
            group.append(y)
    return track


def _placed(geometry: "WindowGeometry", transfers: dict, placing: np.ndarray, group: List[int], v: int) -> bool:
    """Whether members ``group`` place a point in view v: a homography from one of them, or two
    epipolar lines that cross (:func:`.support.lines_cross`)."""
    view = geometry.view_index
    lines = []
    for m in group:
        a = int(view[m])
        if not placing[min(a, v), max(a, v)]:
            continue
        kind, mapped = placed_in(transfers, geometry, a, v, np.array([m]))
        if kind == "point":
            return True
        lines.append(mapped[0])
    if len(lines) < 2:
        return False
    first, second = zip(*itertools.combinations(lines, 2))  # a track's few members: a handful of pairs
    return bool(lines_cross(np.array(first), np.array(second)).any())
