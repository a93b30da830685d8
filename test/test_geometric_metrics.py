"""Scores against the true cameras (gcn_match_ros.geometric_metrics): known answers on exact scenes."""
import numpy as np
import pytest

from gcn_match_ros.geometric_metrics import (GeometricTolerance, chance_pass_rate, consistent_tracks,
                                             pair_epipolar_px, pairs_consistent, score_geometric, view_overlap)
from gcn_match_ros.geometry import project
from gcn_match_ros.problem import Problem, Result

from conftest import look_at

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])


def scene(n_views=3, points=40, seed=0, spread=1.0):
    """Cameras on an arc looking at the origin, every point seen by every view, keypoint i of
    each view = point i (exact projections)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (points, 3)) * [1.0, 0.3, 1.0]
    Rs, ts, kps = [], [], []
    for v in range(n_views):
        a = spread * (v - (n_views - 1) / 2) * 0.25
        R, t = look_at(np.array([6 * np.sin(a), -6 * np.cos(a), 0.5]), np.zeros(3))
        uv, _ = project(K, R, t, X)
        Rs.append(R), ts.append(t), kps.append(uv)
    return Problem(view_offsets=np.arange(n_views + 1) * points, keypoints=np.concatenate(kps),
                   descriptors=np.ones((n_views * points, 4)), K=np.repeat(K[None], n_views, 0),
                   R=np.stack(Rs), t=np.stack(ts), image_size=np.repeat([[640, 480]], n_views, 0))


def test_true_pairs_lie_on_their_epipolar_lines_and_swapped_ones_do_not():
    p = scene()
    n = 40
    rows, cols = np.arange(n), n + np.arange(n)
    assert pair_epipolar_px(p, rows, cols).max() < 1e-3  # keypoints are float32
    assert pairs_consistent(p, rows, cols).all()
    wrong = n + np.roll(np.arange(n), 7)
    far = pair_epipolar_px(p, rows, wrong)
    assert np.median(far) > 5.0
    assert pairs_consistent(p, rows, wrong).mean() < 0.2


def test_a_track_keeps_its_largest_consistent_subset():
    p = scene(n_views=4, points=10)
    track = np.full(p.n_keypoints, -1)
    for v in range(4):
        track[v * 10 + 0] = 0  # point 0 in every view: consistent
    track[[1, 11, 21]] = 1     # point 1 in views 0..2 ...
    track[30 + 5] = 1          # ... and point 5 in view 3: one wrong member
    track[[2, 13]] = 2         # two different points: a wrong pair
    kept = consistent_tracks(p, track)
    assert (kept[[0, 10, 20, 30]] == 0).all()
    assert (kept[[1, 11, 21]] == 1).all() and kept[35] == -1
    assert kept[2] == -1 and kept[13] == -1


def test_score_counts_every_pair_of_the_tracks_and_splits_by_separation():
    p = scene(n_views=3, points=20)
    track = np.full(p.n_keypoints, -1)
    track[[0, 20, 40]] = 0           # 3 consistent pairs
    track[[1, 22]] = 1               # one wrong pair, views 0-1
    res = Result(track=track, pair_rows=[], pair_cols=[], pair_scores=[])
    g = score_geometric(p, res, view_numbers=[2, 4, 6])
    assert g.summary()["pairs"] == 4 and g.summary()["consistent"] == 3
    assert g.precision == pytest.approx(0.75) and g.summary()["tracks3"] == 1
    assert g.by_separation() == {2: (3, 2), 4: (1, 1)}
    with pytest.raises(ValueError, match="view_numbers"):
        score_geometric(p, res, view_numbers=[1, 2])


def test_chance_rate_is_small_and_counts_every_view_pair():
    p = scene(n_views=3, points=60)
    rates = chance_pass_rate(p, pairs=300)
    assert set(rates) == {1, 2} and rates[1][0] == 600 and rates[2][0] == 300
    assert all(hits / tried < 0.2 for tried, hits in rates.values())


def test_view_overlap_from_frusta():
    p = scene(n_views=2)
    ov = view_overlap(p, (4.0, 8.0))
    assert ov[0, 0] == 1.0 and ov[0, 1] > 0.5
    away = scene(n_views=2)
    R, t = look_at(np.array([0.0, -6.0, 0.5]), np.array([0.0, -20.0, 0.5]))  # turned around
    away.R[1], away.t[1] = R, t
    assert view_overlap(away, (4.0, 8.0))[0, 1] == 0.0


def test_a_problem_without_cameras_is_refused():
    p = scene()
    bare = Problem(view_offsets=p.view_offsets, keypoints=p.keypoints, descriptors=p.descriptors)
    with pytest.raises(ValueError, match="no cameras"):
        pair_epipolar_px(bare, [0], [40])
    assert GeometricTolerance().epipolar_px == 2.0
