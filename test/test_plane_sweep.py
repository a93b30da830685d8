"""Plane-sweep depth (gcn_match_ros.plane_sweep) and photometric pose labels
(datasets.label_photometric) on rendered views of a textured plane with known poses."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from gcn_match_ros.data.labels import label_photometric
from gcn_match_ros.data.plane_sweep import SweepConfig, lift, project_in_front as project

from conftest import look_at

SIZE = (640, 480)
TEXTURE_M_PER_PX = 0.01


@pytest.fixture(scope="module")
def plane_views():
    """Four cameras 10 m from a textured plane (world y = 0), 8 deg apart, and their images."""
    rng = np.random.default_rng(0)
    h, w = 1000, 1200
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 3.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)
    s = TEXTURE_M_PER_PX
    # texture pixel (u, v) -> world (X, 0, Z), texture centre at the origin, v down = Z down
    S = np.array([[s, 0, -s * w / 2], [0, 0, 0], [0, -s, s * h / 2]])
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    poses = [look_at(np.array([10 * np.sin(a), -10 * np.cos(a), 0.3]), np.zeros(3))
             for a in np.radians([-12, -4, 4, 12])]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    images = [cv2.warpPerspective(texture, K @ (Rv @ S + np.outer(tv, [0, 0, 1])), SIZE, flags=cv2.INTER_LINEAR)
              for Rv, tv in zip(R, t)]
    return np.stack([K] * 4), R, t, [im.astype(np.float32) for im in images]


def _plane_points(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-2.5, 2.5, n), np.zeros(n), rng.uniform(-1.8, 1.8, n)]


def test_lift_recovers_points_on_the_plane(plane_views) -> None:
    K, R, t, images = plane_views
    X = _plane_points(40, 1)
    xy = project(K[1], R[1], t[1], X)
    points, depth = lift(images, K, R, t, 1, xy, [0, 2], (5.0, 30.0))
    ok = np.isfinite(depth)
    assert ok.mean() > 0.9  # textured everywhere: almost every keypoint is lifted
    # placed within the fine grid's reach: sub-pixel in the other views
    for u in (0, 2, 3):
        err = np.linalg.norm(project(K[u], R[u], t[u], points[ok]) - project(K[u], R[u], t[u], X[ok]), axis=1)
        assert np.max(err) < 0.6, (u, np.max(err))


def test_lift_refuses_flat_patches_and_checks_arguments(plane_views) -> None:
    K, R, t, images = plane_views
    flat = [np.full_like(im, 128.0) for im in images]
    X = _plane_points(5, 2)
    _, depth = lift(flat, K, R, t, 1, project(K[1], R[1], t[1], X), [0, 2], (5.0, 30.0))
    assert np.all(np.isnan(depth))
    with pytest.raises(ValueError, match="support views"):
        lift(images, K, R, t, 1, np.zeros((1, 2)), [], (5.0, 30.0))
    with pytest.raises(ValueError, match="z_min < z_max"):
        lift(images, K, R, t, 1, np.zeros((1, 2)), [0], (30.0, 5.0))
    points, depth = lift(images, K, R, t, 1, np.zeros((0, 2)), [0, 2], (5.0, 30.0))
    assert points.shape == (0, 3) and depth.shape == (0,)


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
