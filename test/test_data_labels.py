"""Tests of gcn_match_ros.data.labels: homography, pose and photometric ground-truth labels."""
from __future__ import annotations

import numpy as np
import pytest

from gcn_match_ros.data.labels import label_homography, label_photometric, label_poses
from gcn_match_ros.data.plane_sweep import SweepConfig, project_in_front as project
from gcn_match_ros.data.scenes import read_oxford
from gcn_match_ros.problem import load_problem

from conftest import (PLANE_IMAGE_SIZE as SIZE, REFERENCE_PROBLEMS as REFERENCE, SHARED_DATA as DATA, look_at,
                      need_shared as _need, plane_points as _plane_points, rigid_motion_2d as _similarity)


def _apply(H: np.ndarray, xy) -> np.ndarray:
    h = np.c_[np.atleast_2d(xy), np.ones(len(np.atleast_2d(xy)))] @ H.T
    return h[:, :2] / h[:, 2:]


# --------------------------------------------------------------------------------------
# Homography labelling
# --------------------------------------------------------------------------------------
def test_homography_labels_synthetic() -> None:
    # views 1, 2 map to view 0 by rigid motions; points are given in view-0 pixels
    to0 = np.stack([np.eye(3), _similarity(0, 30, 20), _similarity(10, -20, 15)])
    from0 = [np.linalg.inv(H) for H in to0]
    sizes = np.array([[400, 300]] * 3)
    rng = np.random.default_rng(1)
    views: list = [[], [], []]
    names: list = [[], [], []]

    def put(v: int, name: str, xy0, offset=(0.0, 0.0)) -> None:
        views[v].append(_apply(from0[v], xy0)[0] + np.asarray(offset))
        names[v].append(name)

    for k, xy in enumerate([(120, 100), (200, 150), (260, 90)]):  # tracks in all views, noisy
        for v in range(3):
            put(v, f"T{k}.{v}", xy, rng.uniform(-0.35, 0.35, 2))
    put(0, "B0", (150, 220))  # B: linked in views 0-1, its view-2 keypoint is 5 px off
    put(1, "B1", (150, 220))
    put(2, "B2", (150, 220), (5.0, 0.0))
    put(0, "C", (320, 250))  # alone: nothing within 10 px anywhere
    put(0, "D0", (80, 240))  # D: 20 px apart -> two unmatched keypoints
    put(1, "D1", (100, 240))
    # a chain p-r-s-q with p, q both in view 0 -> the whole component is unlabelled
    put(0, "p", (300, 180))
    put(0, "q", (304, 180))
    put(1, "r", (301.5, 180))
    put(2, "s", (302.5, 180))
    # u projects just outside image 1 (x = -3): image 1's keypoint at x = 2 does not make u
    # unlabelled, but u (seen from image 1, inside image 0) does make that keypoint unlabelled
    put(0, "u", _apply(to0[1], (-3.0, 60.0))[0])
    put(1, "w", _apply(to0[1], (2.0, 60.0))[0])

    gt = label_homography([np.array(v) for v in views], to0, sizes)
    label = dict(zip(sum(names, []), gt.tolist()))
    tracks = [{label[f"T{k}.{v}"] for v in range(3)} for k in range(3)]
    assert all(len(ids) == 1 and min(ids) >= 0 for ids in tracks)
    assert len(set.union(*tracks)) == 3
    assert label["B0"] == label["B1"] >= 0 and label["B2"] == -2
    assert label["C"] == -1 and label["D0"] == -1 and label["D1"] == -1
    assert label["p"] == label["q"] == label["r"] == label["s"] == -2
    assert label["u"] == -1 and label["w"] == -2


def test_homography_labels_match_reference_problem() -> None:
    path = _need(REFERENCE / "oxford_graf_sift_123.npz")
    ref = load_problem(path)
    scene = read_oxford(_need(DATA / "oxford" / "graf"))
    kps = [ref.keypoints[ref.view_slice(v)] for v in range(ref.n_views)]
    gt = label_homography(kps, scene.homographies[[0, 1, 2]], scene.image_sizes[[0, 1, 2]])
    np.testing.assert_array_equal(gt, ref.gt_track)


# --------------------------------------------------------------------------------------
# Pose labelling
# --------------------------------------------------------------------------------------
def _project(K, R, t, X) -> np.ndarray:
    h = (np.atleast_2d(X) @ R.T + t) @ K.T
    return h[:, :2] / h[:, 2:]


def _epipolar_gaps(K, R, t, a: int, b: int, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """(n_a, n_b) larger point-to-epipolar-line distance of every pair (test oracle, built as
    F = [e_b]x P_b P_a^+ rather than from the essential matrix as the module does)."""
    P_a, P_b = K[a] @ np.c_[R[a], t[a]], K[b] @ np.c_[R[b], t[b]]
    e_b = P_b @ np.r_[-R[a].T @ t[a], 1.0]
    F = np.cross(e_b, (P_b @ np.linalg.pinv(P_a)).T).T  # [e_b]x M, column by column
    h_a, h_b = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    l_b, l_a = h_a @ F.T, h_b @ F
    alg = np.abs(l_b @ h_b.T)
    return np.maximum(alg / np.hypot(l_b[:, :1], l_b[:, 1:2]), alg / np.hypot(l_a[:, 0], l_a[:, 1]))


@pytest.fixture(scope="module")
def rig():
    """Three cameras 10 m from the origin, 20 deg apart, and 12 points near the origin."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    poses = [look_at(np.array([10 * np.sin(a), -10 * np.cos(a), 0.5]), np.zeros(3))
             for a in np.radians([-20, 0, 20])]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    X = np.random.default_rng(3).uniform(-2, 2, (12, 3))
    return np.stack([K] * 3), R, t, X


def test_pose_labels_synthetic(rig) -> None:
    K, R, t, X = rig
    views = [list(_project(K[v], R[v], t[v], X)) for v in range(3)]
    # Q: seen by all cameras, but its view-2 keypoint is 4 px off -> nothing confirms Q
    Q = np.array([0.5, 0.3, 2.5])
    for v in range(3):
        views[v].append(_project(K[v], R[v], t[v], Q)[0] + (np.array([0.0, 4.0]) if v == 2 else 0))
    # Z lies behind cameras 0 and 1 (its "projections" there are mirrored) and in front of
    # camera 2: it triangulates and reprojects exactly, but is no scene point
    Z = np.array([-5.0, -10.5, 0.5])
    for v in range(3):
        views[v].append(_project(K[v], R[v], t[v], Z)[0])
    # a distractor in view 0, more than 10 px from the epipolar line of every keypoint elsewhere
    grid = np.stack(np.meshgrid(np.arange(5, 640, 15), np.arange(5, 480, 15)), -1).reshape(-1, 2)
    free = np.ones(len(grid), dtype=bool)
    for b in (1, 2):
        free &= (_epipolar_gaps(K, R, t, 0, b, grid, np.array(views[b])) > 12).all(axis=1)
    assert free.any(), "test setup: no free spot for a distractor"
    views[0].append(grid[np.flatnonzero(free)[0]])
    gt = label_poses([np.array(v) for v in views], K, R, t)
    n = len(X)
    per_view = np.split(gt, np.cumsum([len(v) for v in views])[:-1])
    points = np.stack([g[:n] for g in per_view])
    assert np.all(points >= 0) and np.all(points == points[0])  # every point is one track ...
    assert len(np.unique(points[0])) == n  # ... of its own
    assert all(g[n] == -2 for g in per_view)  # Q: epipolar candidates, never confirmed
    assert all(g[n + 1] < 0 for g in per_view)  # Z: fails the cheirality test
    assert per_view[0][n + 2] == -1  # the distractor


@pytest.fixture(scope="module")
def ring():
    """Five cameras 10 m from the origin, 15 deg apart, and 6 points seen by all."""
    K = np.stack([np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])] * 5)
    poses = [look_at(np.array([10 * np.sin(a), -10 * np.cos(a), 0.5]), np.zeros(3))
             for a in np.radians([-30, -15, 0, 15, 30])]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    return K, R, t, np.random.default_rng(4).uniform(-2, 2, (6, 3))


def test_pose_labels_ambiguous_partner_is_unlabelled(ring) -> None:
    # Y hides behind X on camera 4's ray, so camera 4's keypoint of X has two confirmed
    # partners in views 2 and 3 (X's and Y's)
    K, R, t, P = ring
    X = np.vstack([P, [0.3, -0.4, 0.2]])
    C4 = -R[4].T @ t[4]
    Y = C4 + 0.8 * (X[-1] - C4)
    views = [_project(K[v], R[v], t[v], X) for v in range(5)]
    views[2] = np.vstack([views[2], _project(K[2], R[2], t[2], Y)])
    views[3] = np.vstack([views[3], _project(K[3], R[3], t[3], Y)])
    gt = label_poses(views, K, R, t)
    per_view = np.split(gt, np.cumsum([len(v) for v in views])[:-1])
    ordinary = np.stack([g[:6] for g in per_view])
    assert np.all(ordinary >= 0) and np.all(ordinary == ordinary[0])
    assert per_view[4][6] == -2  # the keypoint with two partners per view ...
    assert np.all(per_view[2][6:] == -2) and np.all(per_view[3][6:] == -2)  # ... and those partners
    # uniqueness drops only the ambiguous links: X keeps its track in views 0 and 1
    assert per_view[0][6] == per_view[1][6] >= 0 and per_view[0][6] not in ordinary[0]


def test_pose_labels_chain_that_does_not_close(ring) -> None:
    # X (views 0-2) and Y (views 2-4) share camera 2's keypoint: every link is unique and
    # confirmed, but X's and Y's keypoints are not epipolar-consistent -> no track
    K, R, t, P = ring
    X = np.array([0.3, -0.4, 0.2])
    C2 = -R[2].T @ t[2]
    Y = C2 + 0.8 * (X - C2)
    views = [np.vstack([_project(K[v], R[v], t[v], P), _project(K[v], R[v], t[v], X if v < 3 else Y)])
             for v in range(5)]
    gt = label_poses(views, K, R, t).reshape(5, 7)
    assert np.all(gt[:, :6] >= 0) and np.all(gt[:, :6] == gt[0, :6])
    assert np.all(gt[:, 6] == -2)


def test_pose_labels_need_three_views(rig) -> None:
    K, R, t, X = rig
    with pytest.raises(ValueError, match="at least 3 views"):
        label_poses([_project(K[v], R[v], t[v], X) for v in range(2)], K[:2], R[:2], t[:2])


# --------------------------------------------------------------------------------------
# Photometric labelling (plane_views: a textured plane, conftest)
# --------------------------------------------------------------------------------------
def test_photometric_labels_on_a_plane(plane_views) -> None:
    K, R, t, images = plane_views
    X = _plane_points(30, 3)
    views = [project(K[v], R[v], t[v], X) for v in range(4)]
    # a keypoint of view 0 whose true position has no keypoint within 10 px in any view
    Y = np.array([[0.9, 0.0, 0.95]])
    gap = min(np.linalg.norm(project(K[v], R[v], t[v], Y) - views[v], axis=1).min() for v in range(4))
    assert gap > 12, "test setup: Y too close to a keypoint"
    # a keypoint of view 3 shifted 6 px off its point: neither linked nor clearly unmatched
    views = [np.r_[views[0], project(K[0], R[0], t[0], Y)], views[1], views[2],
             np.r_[views[3], project(K[3], R[3], t[3], X[:1]) + [6.0, 0.0]]]
    gt = label_photometric(views, images, K, R, t, np.tile(SIZE, (4, 1)), sweep=SweepConfig())
    per_view = np.split(gt, np.cumsum([len(v) for v in views])[:-1])
    tracks = np.stack([g[:30] for g in per_view])
    ok = np.all(tracks >= 0, axis=0) & np.all(tracks == tracks[0], axis=0)
    assert ok.mean() > 0.9 and len(np.unique(tracks[0, ok])) == ok.sum()  # one track per point
    assert per_view[0][30] == -1  # Y: lifted, seen, nothing there
    assert per_view[3][30] == -2  # the shifted copy: 3-10 px from a projection


def test_photometric_labels_without_pose_tracks_are_unlabelled(plane_views) -> None:
    K, R, t, images = plane_views
    rng = np.random.default_rng(5)
    views = [rng.uniform(0, 400, (8, 2)) for _ in range(3)]  # no consistent tracks -> no depth range
    gt = label_photometric(views, images[:3], K[:3], R[:3], t[:3], np.tile(SIZE, (3, 1)))
    assert np.all(gt == -2)
    with pytest.raises(ValueError, match="at least 3 views"):
        label_photometric(views[:2], images[:2], K[:2], R[:2], t[:2], np.tile(SIZE, (2, 1)))
