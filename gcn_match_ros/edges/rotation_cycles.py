"""Cycle consistency of a window's two-view geometry: relative rotations must compose.

Three calibrated views a < b < c whose pairs all have an essential matrix give three relative
rotations, and for any real cameras ``R_bc R_ab = R_ac``. A two-view model can be wrong and
still explain its seeds: on a repetitive facade (rows of identical windows) the matches
shifted by one window are explained by a "ghost" plane behind the real one, and an essential
matrix fitted to both sets agrees with wrong pairs 2–12 px off the true epipolar lines while
its rotation is off by degrees. No estimator, threshold or stricter seed ratio fixes that
(benchmarks/results/model_cycles.md); the window's other views do: such a model does not close
its rotation cycles.

A model is distrusted when it lies in at least one triangle of modelled view pairs and closes
none of them within :data:`ROTATION_CYCLE_DEG` (:func:`broken_cycle_pairs`). Only a model
agreeing with at least :data:`MIN_ROTATION_PAIRS` pairs is tested: a rotation from few pairs of
a small object is uncertain by degrees (a generated 20-point, 3-view window: 4° of cycle error
with every model right). Estimating each rotation's own uncertainty by refitting it to two
halves of its pairs was tried: the spreads (up to tens of degrees) passed every triangle of the
real windows. A failing triangle cannot tell which of its three models is wrong, so when none
of them closes another triangle all three are distrusted (blaming only the least supported one
left castle-P19 at geometric precision 0.829 instead of 0.862; model_cycles.md sorts the models
both ways). Models in no triangle, planar models and uncalibrated views are not tested; the test
is a solver setting, off by default (a small object's rotations are too uncertain for it:
model_cycles.md, generated scenes).
"""
from __future__ import annotations

import itertools
from typing import Dict, Optional, Set, Tuple

import cv2
import numpy as np

__all__ = ["ROTATION_CYCLE_DEG", "MIN_ROTATION_PAIRS", "MIN_CHEIRALITY_POINTS", "rotation_angle_deg", "relative_rotation",
           "cycle_errors", "broken_cycle_pairs"]

#: A triangle closes when R_ac⁻¹ R_bc R_ab turns by at most this (degrees): ~4x the largest cycle
#: error of the development scenes' sound models (median 0.24°, triangle maxima 0.45°).
ROTATION_CYCLE_DEG = 2.0
#: Pairs agreeing with a model needed for its rotation to be tested.
MIN_ROTATION_PAIRS = 60
#: Pairs agreeing with an essential matrix needed to choose its rotation (cheirality).
MIN_CHEIRALITY_POINTS = 5

ViewPair = Tuple[int, int]


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) a rotation matrix turns by.

    Shapes: R (3, 3).
    """
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))))


def relative_rotation(E: np.ndarray, ua: np.ndarray, ub: np.ndarray) -> Optional[np.ndarray]:
    """The rotation of view b relative to view a (``X_b = R X_a + t``) of an essential matrix
    ``u_bᵀ E u_a = 0``: of its four decompositions, the one putting most of the pairs in front
    of both cameras. None with fewer than :data:`MIN_CHEIRALITY_POINTS` pairs or none in front.

    Shapes: E (3, 3); ua, ub (M, 2) calibrated (normalised) image points -> (3, 3).
    """
    if ua.shape[0] < MIN_CHEIRALITY_POINTS:
        return None
    try:
        front, R, _, _ = cv2.recoverPose(np.ascontiguousarray(E, np.float64), np.ascontiguousarray(ua, np.float64),
                                         np.ascontiguousarray(ub, np.float64), np.eye(3))
    except cv2.error:
        return None
    return R if front > 0 else None


def cycle_errors(rotations: Dict[ViewPair, np.ndarray]) -> Dict[Tuple[int, int, int], float]:
    """For every triangle a < b < c of view pairs with a rotation, how far (degrees) the
    rotations are from composing: the angle of ``R_acᵀ R_bc R_ab``.

    Args:
        rotations: (a, b), a < b -> R_ab (3, 3), ``X_b = R_ab X_a + t``.
    """
    views = sorted({v for pair in rotations for v in pair})
    out = {}
    for a, b, c in itertools.combinations(views, 3):
        if (a, b) in rotations and (b, c) in rotations and (a, c) in rotations:
            out[(a, b, c)] = rotation_angle_deg(rotations[(a, c)].T @ rotations[(b, c)] @ rotations[(a, b)])
    return out


def broken_cycle_pairs(rotations: Dict[ViewPair, np.ndarray], tol_deg: float = ROTATION_CYCLE_DEG) -> Set[ViewPair]:
    """The view pairs whose rotation lies in a triangle (:func:`cycle_errors`) and closes none
    within ``tol_deg`` (module docstring)."""
    triangles: Dict[ViewPair, list] = {}
    for (a, b, c), err in cycle_errors(rotations).items():
        for pair in ((a, b), (b, c), (a, c)):
            triangles.setdefault(pair, []).append(err)
    return {pair for pair, errs in triangles.items() if min(errs) > tol_deg}
