"""Tests of gcn_match_ros.edges.rotation_cycles and WindowGeometry.with_closed_rotation_cycles:
relative rotations of a window's essential matrices must compose."""
import cv2
import numpy as np

from conftest import random_rotation
from gcn_match_ros.edges.consistency import WindowGeometry, verified_tracks
from gcn_match_ros.edges.rotation_cycles import (MIN_ROTATION_PAIRS, ROTATION_CYCLE_DEG, broken_cycle_pairs, cycle_errors,
                                                 relative_rotation, rotation_angle_deg)
from gcn_match_ros.edges.verify import PairModel
from gcn_match_ros.geometry import fundamental_from_poses, skew, unproject
from gcn_match_ros.problem import Problem

K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def _turn(axis, deg):
    """Rotation by ``deg`` about ``axis``."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return cv2.Rodrigues(np.radians(deg) * axis)[0]


def _cameras(n, seed=0):
    """n cameras 6 m from the origin looking roughly at it (world -> camera R, t)."""
    rng = np.random.default_rng(seed)
    Rs = [_turn([0, 1, 0], 8.0 * v) @ _turn(rng.normal(size=3), 2.0) for v in range(n)]
    ts = [np.array([0.3 * v, 0.1 * rng.normal(), 6.0]) for v in range(n)]
    return Rs, ts


def _project(R, t, X):
    x = (K @ (R @ X.T + t[:, None])).T
    return x[:, :2] / x[:, 2:]


def test_rotation_angle_of_a_known_turn():
    assert abs(rotation_angle_deg(_turn([0, 0, 1], 30.0)) - 30.0) < 1e-9
    assert rotation_angle_deg(np.eye(3)) == 0.0


def test_relative_rotation_of_an_essential_matrix_is_the_cameras():
    rng = np.random.default_rng(1)
    (Ra, Rb), (ta, tb) = _cameras(2)
    X = rng.uniform(-1, 1, (30, 3))
    R_ab = Rb @ Ra.T
    E = skew(tb - R_ab @ ta) @ R_ab
    ua, ub = (unproject(K, _project(R, t, X))[:, :2] for R, t in ((Ra, ta), (Rb, tb)))
    R = relative_rotation(E, ua, ub)
    assert rotation_angle_deg(R.T @ R_ab) < 1e-4
    assert relative_rotation(E, ua[:4], ub[:4]) is None  # too few pairs to choose the decomposition


def test_cycle_errors_are_zero_for_composing_rotations_and_the_perturbation_otherwise():
    R = {v: random_rotation(np.random.default_rng(v)) for v in range(3)}
    rel = {(a, b): R[b] @ R[a].T for a, b in ((0, 1), (1, 2), (0, 2))}
    assert cycle_errors(rel)[(0, 1, 2)] < 1e-6
    rel[(0, 2)] = _turn([1, 2, 3], 5.0) @ rel[(0, 2)]
    assert abs(cycle_errors(rel)[(0, 1, 2)] - 5.0) < 1e-6


def test_broken_pairs_are_those_closing_no_triangle():
    R = {v: random_rotation(np.random.default_rng(10 + v)) for v in range(5)}
    rel = {(a, b): R[b] @ R[a].T for a in range(4) for b in range(a + 1, 4)}
    rel[(0, 1)] = _turn([0, 0, 1], 5.0) @ rel[(0, 1)]  # wrong: both its triangles fail ...
    rel[(3, 4)] = R[4] @ R[3].T                        # ... (3, 4) is in no triangle: untested
    assert broken_cycle_pairs(rel) == {(0, 1)}         # (0, 2) closes (0, 2, 3): kept
    three = {k: v for k, v in rel.items() if max(k) <= 2}
    assert broken_cycle_pairs(three) == {(0, 1), (1, 2), (0, 2)}  # one failing triangle: all three
    small = {(0, 1): _turn([0, 0, 1], 0.5 * ROTATION_CYCLE_DEG) @ (R[1] @ R[0].T), (1, 2): R[2] @ R[1].T,
             (0, 2): R[2] @ R[0].T}
    assert broken_cycle_pairs(small) == set()


def _window_with_a_ghost_model(n_views=4, p=MIN_ROTATION_PAIRS + 10, seed=2):
    """Views 0..n-1 of p points. The last view also holds p keypoints projected by a wrong
    camera (turned 6°), and its pair with view 0 has that camera's model and pairs: a model
    explaining its pairs exactly whose rotation is wrong. Every other pair is the truth."""
    rng = np.random.default_rng(seed)
    Rs, ts = _cameras(n_views, seed)
    X = rng.uniform(-1, 1, (p, 3))
    last = n_views - 1
    R_ghost = _turn([0, 1, 0], 6.0) @ Rs[last]
    kps = [_project(Rs[v], ts[v], X) for v in range(n_views)]
    kps[last] = np.vstack([kps[last], _project(R_ghost, ts[last], X)])
    sizes = [len(k) for k in kps]
    off = np.r_[0, np.cumsum(sizes)]
    problem = Problem(view_offsets=off, keypoints=np.concatenate(kps), descriptors=rng.normal(size=(off[-1], 8)),
                      K=np.stack([K] * n_views))
    models, rows, cols = {}, [], []
    for a in range(n_views):
        for b in range(a + 1, n_views):
            ghost = a == 0 and b == last
            Rb = R_ghost if ghost else Rs[b]
            F = fundamental_from_poses(K, Rs[a], ts[a], K, Rb, ts[b])
            models[(a, b)] = PairModel(None, F / np.linalg.norm(F), seeds=p, inliers_f=p, essential=True,
                                       epipolar_px=1.0)
            rows.append(off[a] + np.arange(p))
            cols.append(off[b] + np.arange(p) + (p if ghost else 0))
    return problem, models, np.concatenate(rows), np.concatenate(cols)


def test_the_model_that_closes_no_rotation_cycle_is_dropped():
    problem, models, rows, cols = _window_with_a_ghost_model()
    geometry = WindowGeometry(problem, models)
    assert geometry.agree(rows, cols).all()  # every model explains its pairs: agreement cannot tell
    closed = geometry.with_closed_rotation_cycles(rows, cols)
    assert set(closed.models) == set(models) - {(0, 3)}
    assert closed.unverified[0, 3] and not closed.unverified[1, 3]


def test_a_lone_failing_triangle_drops_all_three_models_and_verified_tracks_uses_the_check():
    problem, models, rows, cols = _window_with_a_ghost_model(n_views=3)
    closed = WindowGeometry(problem, models).with_closed_rotation_cycles(rows, cols)
    assert closed.models == {}
    scores = np.full(rows.shape, 0.8)
    keep, _ = verified_tracks(WindowGeometry(problem, models), rows, cols, scores, 0.5, rotation_cycles=True)
    assert not keep.any()  # unverified view pairs keep only pairs scored >= 0.9
    keep, _ = verified_tracks(WindowGeometry(problem, models), rows, cols, scores, 0.5)
    assert keep.all()


def test_uncalibrated_or_consistent_windows_are_left_as_they_are():
    problem, models, rows, cols = _window_with_a_ghost_model()
    uncalibrated = Problem(view_offsets=problem.view_offsets, keypoints=problem.keypoints,
                           descriptors=problem.descriptors)
    geometry = WindowGeometry(uncalibrated, {k: m for k, m in models.items()})
    assert geometry.with_closed_rotation_cycles(rows, cols) is geometry
    sound = {k: m for k, m in models.items() if k != (0, 3)}
    geometry = WindowGeometry(problem, sound)
    assert geometry.with_closed_rotation_cycles(rows, cols) is geometry


def test_a_model_with_too_few_agreeing_pairs_is_not_tested():
    problem, models, rows, cols = _window_with_a_ghost_model(p=MIN_ROTATION_PAIRS - 1)
    geometry = WindowGeometry(problem, models)
    assert geometry.with_closed_rotation_cycles(rows, cols) is geometry
