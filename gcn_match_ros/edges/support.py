"""Two-view tracks the window's other views should have joined: third-view support.

A track of two members is a point matched in views i and j only. Where other views k are
verified against both i and j, their trusted models place that point in k: with a homography,
H x (from either side); else where the two epipolar lines of its keypoints cross in k (lines
within :data:`MIN_CROSSING_DEG` of parallel place nothing). A real point landing inside view k
is mostly detected and matched there as well, so a track of two that lands inside at least
:data:`MIN_EXPECTED` such views and was joined by none of them is *unsupported*: it is what is
left of a match no other view confirms — on a facade, the window next to the right one, which
every two-view model accepts. An unsupported track is kept only when its pair scores at least
the solver's ``support_threshold``.

Measured on the development scenes of benchmarks/geometric_eval.py (gcn, SIFT, every pair of
every track against the true cameras): pairs of tracks of two that no other view is expected to
show are 0.990 consistent, those expected in at least one view 0.932, in at least two 0.923;
tracks of three or more 0.961. MIN_EXPECTED and the threshold were chosen on those scenes by a
rule fixed before (the highest precision among settings keeping at least 99 % of the consistent
pairs of the rule off), from MIN_EXPECTED 1 or 2 and thresholds 0.6 / 0.7 / 0.8 / 1 (all);
precision / share of consistent pairs kept: off 0.9647 / 1; at least 1 view: 0.9667 / 0.995,
0.9675 / 0.988, 0.9684 / 0.980, 0.9676 / 0.920; **at least 2 views**: 0.9659 / 0.998,
0.9665 / 0.995, **0.9670 / 0.991 (0.8)**, 0.9667 / 0.958. (castle-P19's figures for the same
grid came out of the same diagnostic run, before the rule was written down.)

**Off by default** (``support_threshold`` = 0): it assumes that a point inside a view is seen
there, which occlusion breaks — on generated scenes with partial visibility it costs F1 (partial
preset, 4 views: 0.852 -> 0.820; benchmarks/results/generated_eval.md) — and for the shipped ORB
model no threshold keeps 99 % of the development scenes' consistent pairs (0.7: 98 %). With
SIFT on the held-out castle-P19 (repeated facades, little occlusion between neighbouring
views) 0.8 lifts geometric precision 0.909 -> 0.912 and separation 3 0.84 -> 0.86 at 1.51x
nn-ransac's consistent pairs (benchmarks/results/geometric_eval.md).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..rounding import track_members
from ..view_pairs import by_view_pair

if TYPE_CHECKING:  # consistency imports this module
    from .consistency import WindowGeometry

__all__ = ["MIN_EXPECTED", "MIN_CROSSING_DEG", "expected_views", "unsupported_tracks"]

#: views a track of two must be expected in (and absent from) to be unsupported
MIN_EXPECTED = 2
#: epipolar lines crossing at a smaller angle place a point too loosely to expect it
MIN_CROSSING_DEG = 5.0


def _placed_in(transfers: dict, geometry: "WindowGeometry", view: int, other: int, x: np.ndarray):
    """What the model of (view, other) makes of keypoints ``x`` (indices) of ``view`` in ``other``:
    ('point', (n, 2)) under a homography, ('line', (n, 3)) under F
    (:meth:`.consistency.WindowGeometry.transfers`, computed once per view pair into ``transfers``)."""
    a, b = min(view, other), max(view, other)
    if (a, b) not in transfers:
        transfers[a, b] = geometry.transfers(a, b)
    fwd, bwd, planar, _ = transfers[a, b]
    mapped = (fwd if view == a else bwd)[x - geometry.problem.view_offsets[view]]
    return ("point", mapped[:, :2]) if planar else ("line", mapped)


def _crossings(la: np.ndarray, lb: np.ndarray) -> np.ndarray:
    """Where lines la[m] and lb[m] cross (NaN where they are within MIN_CROSSING_DEG of parallel).

    Shapes: (n, 3), (n, 3) -> (n, 2)."""
    na = la[:, :2] / np.maximum(np.linalg.norm(la[:, :2], axis=1, keepdims=True), 1e-12)
    nb = lb[:, :2] / np.maximum(np.linalg.norm(lb[:, :2], axis=1, keepdims=True), 1e-12)
    sine = np.abs(na[:, 0] * nb[:, 1] - na[:, 1] * nb[:, 0])
    x = np.cross(la, lb)
    ok = (sine >= np.sin(np.radians(MIN_CROSSING_DEG))) & (np.abs(x[:, 2]) > 1e-12)
    out = np.full((la.shape[0], 2), np.nan)
    out[ok] = x[ok, :2] / x[ok, 2:3]
    return out


def _bounds(geometry: "WindowGeometry", view: int) -> np.ndarray:
    """(4,) x0, y0, x1, y1 of a view: its image, or where its keypoints lie if its size is unknown."""
    size = geometry.problem.image_size
    if size is not None:
        return np.array([0.0, 0.0, float(size[view][0]), float(size[view][1])])
    kp = geometry.keypoints[geometry.problem.view_offsets[view]:geometry.problem.view_offsets[view + 1]]
    return np.r_[kp.min(0), kp.max(0)] if kp.size else np.zeros(4)


def expected_views(geometry: "WindowGeometry", rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """How many other views verified against both views of each pair place its point inside
    themselves (module docstring).

    Args:
        geometry: the window's :class:`.consistency.WindowGeometry`.
        rows, cols: (M,) keypoint indices of pairs (different views).

    Returns:
        (M,) int64.
    """
    rows, cols, va, vb = geometry.in_view_order(rows, cols)
    count = np.zeros(rows.shape[0], np.int64)
    verified = geometry.verified & geometry.checkable
    transfers: dict = {}
    for (i, j), m in by_view_pair(va, vb).items():
        for k in np.flatnonzero(verified[i] & verified[j]).tolist():
            if k in (i, j):
                continue
            kind_a, pa = _placed_in(transfers, geometry, i, k, rows[m])
            kind_b, pb = _placed_in(transfers, geometry, j, k, cols[m])
            x = pa if kind_a == "point" else pb if kind_b == "point" else _crossings(pa, pb)
            x0, y0, x1, y1 = _bounds(geometry, k)
            with np.errstate(invalid="ignore"):
                count[m] += (x[:, 0] >= x0) & (x[:, 0] < x1) & (x[:, 1] >= y0) & (x[:, 1] < y1)
    return count


def unsupported_tracks(geometry: "WindowGeometry", track: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                       scores: np.ndarray, threshold: float, min_expected: int = MIN_EXPECTED) -> np.ndarray:
    """The tracks of two whose point at least ``min_expected`` other views should show and whose
    pair scores below ``threshold`` (module docstring).

    Args:
        geometry: the window's :class:`.consistency.WindowGeometry`.
        track: (N,) track of every keypoint (-1: none).
        rows, cols, scores: (M,) the pairs the tracks were merged from, with their scores.
        threshold: the score an unsupported track needs.
        min_expected: the views a track must be expected in to be judged.

    Returns:
        (T,) ids of the tracks to dissolve (empty: none).
    """
    members, starts = track_members(track)
    first = starts[:-1][np.diff(starts) == 2]
    a, b = members[first], members[first + 1]  # a < b: members in keypoint order
    two = np.asarray(track, np.int64)[a]
    if two.size == 0:
        return two
    n = track.shape[0]
    key = np.minimum(rows, cols) * n + np.maximum(rows, cols)
    if key.size == 0:
        return two[:0]
    order = np.argsort(key)
    key, scores = key[order], np.asarray(scores)[order]
    at = np.minimum(np.searchsorted(key, a * n + b), key.size - 1)  # a < b: members in index order
    # a member exchanged for a near-duplicate after the merge (.duplicates) has no scored pair
    weak = (key[at] == a * n + b) & (scores[at] < threshold)
    if not weak.any():
        return two[:0]
    expected = np.zeros(two.size, np.int64)
    expected[weak] = expected_views(geometry, a[weak], b[weak])
    return two[weak & (expected >= min_expected)]
