"""Tests of gcn_match_ros.edges.support (third-view support of tracks of two): known answers from
true cameras."""
import numpy as np
import pytest
from conftest import look_at

from gcn_match_ros.edges.consistency import WindowGeometry, verified_tracks
from gcn_match_ros.edges.support import MIN_EXPECTED, expected_views, unsupported_tracks
from gcn_match_ros.edges.verify import PairModel
from gcn_match_ros.geometry import fundamental_from_poses, project
from gcn_match_ros.problem import Problem

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
SIZE = (640, 480)


def _cameras(n=4):
    """n cameras around a circle in front of the origin (no three centres on a line)."""
    poses = [look_at(np.array([2.0 * np.cos(a), 2.0 * np.sin(a), -6.0]), np.zeros(3), down=(0.0, 1.0, 0.0))
             for a in np.radians(90.0 * np.arange(n))]
    return np.array([R for R, _ in poses]), np.array([t for _, t in poses])


def _window(points, n_views=4):
    """Every point projected into every view (keypoints in point order per view), and the
    window's true epipolar models: each view pair verified by its fundamental matrix."""
    R, t = _cameras(n_views)
    views = [project(K, R[v], t[v], points)[0] for v in range(n_views)]
    n = len(points)
    problem = Problem(view_offsets=np.arange(n_views + 1) * n, keypoints=np.concatenate(views).astype(np.float32),
                      descriptors=np.zeros((n * n_views, 8), np.float32),
                      image_size=np.tile(np.array(SIZE), (n_views, 1)))
    models = {(a, b): PairModel(H=None, F=fundamental_from_poses(K, R[a], t[a], K, R[b], t[b]), planar=False,
                                seeds=20, inliers_f=20, epipolar_px=1.0)
              for a in range(n_views) for b in range(a + 1, n_views)}
    return problem, WindowGeometry(problem, models)


#: points near the origin, every one seen by every camera; enough per view for a model (MIN_SEEDS)
POINTS = np.random.default_rng(0).uniform(-0.8, 0.8, (14, 3))


def test_a_point_matched_in_two_views_is_expected_in_every_other_view_that_sees_it():
    problem, geometry = _window(POINTS)
    n = len(POINTS)
    rows, cols = np.arange(n), n + np.arange(n)  # the true pairs of views 0 and 1
    assert (expected_views(geometry, rows, cols) == 2).all()  # views 2 and 3 see every point
    # the same answer whichever keypoint comes first
    assert (expected_views(geometry, cols, rows) == 2).all()


def test_a_point_the_crossing_lines_place_outside_a_view_is_not_expected_there():
    far = np.array([[40.0, 0.0, 0.0]])  # seen by view 0 and 1, far outside the other views' images
    problem, geometry = _window(np.r_[POINTS, far])
    n = len(POINTS) + 1
    assert expected_views(geometry, np.array([n - 1]), np.array([2 * n - 1]))[0] < 2


def test_a_view_without_a_model_towards_both_views_places_nothing():
    problem, geometry = _window(POINTS)
    del geometry.models[(1, 2)]
    geometry = WindowGeometry(problem, geometry.models)
    n = len(POINTS)
    assert (expected_views(geometry, np.arange(n), n + np.arange(n)) == 1).all()  # only view 3 left


def test_a_homography_places_the_point_from_either_side():
    xa = np.r_[[[100.0, 100.0], [600.0, 100.0]], np.c_[np.arange(12) * 20.0 + 50, np.full(12, 300.0)]]
    shift = np.array([[1.0, 0, 30.0], [0, 1.0, 0], [0, 0, 1.0]])
    views = [xa, xa + [30.0, 0], xa + [60.0, 0]]
    n = len(xa)
    problem = Problem(view_offsets=np.arange(4) * n, keypoints=np.concatenate(views).astype(np.float32),
                      descriptors=np.zeros((3 * n, 8), np.float32), image_size=np.tile(np.array(SIZE), (3, 1)))
    geometry = WindowGeometry(problem, {k: PairModel(H=Hk, F=None, planar=True, seeds=12, inliers_h=12)
                                        for k, Hk in {(0, 1): shift, (0, 2): shift @ shift, (1, 2): shift}.items()})
    # the first point lands at x = 160 in view 2, the second at x = 660: outside its 640 px
    assert expected_views(geometry, np.array([0, 1]), np.array([n, n + 1])).tolist() == [1, 0]


def _two_view_tracks(problem):
    n = problem.view_offsets[1]
    track = np.full(problem.n_keypoints, -1, np.int64)
    track[:n] = track[n:2 * n] = np.arange(n)
    return track, np.arange(n), n + np.arange(n)


def test_a_weak_track_of_two_the_other_views_should_show_is_unsupported():
    problem, geometry = _window(POINTS)
    track, rows, cols = _two_view_tracks(problem)
    scores = np.full(len(POINTS), 0.9)
    scores[[0, 2]] = [0.5, 0.7]
    assert MIN_EXPECTED <= 2
    assert unsupported_tracks(geometry, track, rows, cols, scores, 0.8).tolist() == [0, 2]
    assert unsupported_tracks(geometry, track, rows, cols, scores, 0.8, min_expected=3).tolist() == []


def test_tracks_joined_by_a_third_view_or_without_a_scored_pair_are_supported():
    problem, geometry = _window(POINTS)
    n = len(POINTS)
    track, rows, cols = _two_view_tracks(problem)
    track[2 * n] = 0  # view 2 joined track 0: three members
    scores = np.zeros(n)
    assert unsupported_tracks(geometry, track, rows, cols, scores, 0.8).tolist() == list(range(1, n))
    # track 1's pair is not among the scored pairs (a member exchanged after the merge)
    assert unsupported_tracks(geometry, track, rows[2:], cols[2:], scores[2:], 0.8).tolist() == list(range(2, n))


@pytest.mark.parametrize("threshold, kept", [(0.0, 14), (0.8, 12)])
def test_verified_tracks_dissolves_unsupported_tracks_only_when_asked(threshold, kept):
    problem, geometry = _window(POINTS)
    n = len(POINTS)
    rows, cols = np.arange(n), n + np.arange(n)
    scores = np.full(n, 0.9)
    scores[[0, 2]] = [0.5, 0.7]
    keep, track = verified_tracks(geometry, rows, cols, scores, 0.5, support_threshold=threshold)
    assert keep.all()
    assert len(set(track[track >= 0].tolist())) == kept
    assert track.max() == kept - 1  # renumbered
    assert (track[rows] == track[cols]).all()  # a track of two kept whole, or dissolved whole
    assert (track[rows[[0, 2]]] < 0).all() == (threshold > 0)


def test_without_image_sizes_a_view_is_where_its_keypoints_lie():
    problem, geometry = _window(POINTS)
    n = len(POINTS)
    kp = problem.keypoints.reshape(4, n, 2)
    lo, hi = kp[2:].min(axis=1), kp[2:].max(axis=1)  # views 2 and 3: their keypoints' extent
    interior = ((kp[2:] > lo[:, None] + 1) & (kp[2:] < hi[:, None] - 1)).all(axis=(0, 2))
    assert interior.sum() >= 4
    problem.image_size = None
    rows, cols = np.arange(n), n + np.arange(n)
    expected = expected_views(WindowGeometry(problem, geometry.models), rows, cols)
    assert (expected[interior] == 2).all()
