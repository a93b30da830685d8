"""Tests of gcn_match_ros.data.plane_sweep: depth of keypoints on rendered views of a textured plane."""
from __future__ import annotations

import numpy as np
import pytest

from gcn_match_ros.data.plane_sweep import lift, project_in_front as project

from conftest import plane_points as _plane_points


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
