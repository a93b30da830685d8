"""Tests of gcn_match_ros.edges.placement (keypoints a track's members place point to point join at
the point-to-point threshold): known answers from true cameras."""
import numpy as np
from conftest import look_at

from gcn_match_ros.edges.consistency import TrackCheck, WindowGeometry, verified_tracks
from gcn_match_ros.edges.placement import placed_members
from gcn_match_ros.edges.verify import PairModel
from gcn_match_ros.geometry import fundamental_from_poses, homogeneous, project
from gcn_match_ros.problem import Problem

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
SIZE = (640, 480)
#: points near the origin, every one seen by every camera; enough per view for a model (MIN_SEEDS)
POINTS = np.random.default_rng(1).uniform(-0.8, 0.8, (14, 3))
N = len(POINTS)


def _window(centres, keypoints=None, points=POINTS):
    """Three cameras at ``centres`` looking at the origin, every point in every view (keypoints in
    point order; ``keypoints`` replaces view 2's), each view pair verified by its true F."""
    poses = [look_at(np.asarray(c, np.float64), np.zeros(3), down=(0.0, 1.0, 0.0)) for c in centres]
    R, t = np.array([p[0] for p in poses]), np.array([p[1] for p in poses])
    views = [project(K, R[v], t[v], points)[0] for v in range(3)]
    if keypoints is not None:
        views[2] = keypoints
    n = len(points)
    problem = Problem(view_offsets=np.arange(4) * n, keypoints=np.concatenate(views).astype(np.float32),
                      descriptors=np.zeros((3 * n, 8), np.float32), image_size=np.tile(np.array(SIZE), (3, 1)))
    models = {(a, b): PairModel(H=None, F=fundamental_from_poses(K, R[a], t[a], K, R[b], t[b]), planar=False,
                                seeds=20, inliers_f=20, epipolar_px=1.0)
              for a in range(3) for b in range(a + 1, 3)}
    return problem, WindowGeometry(problem, models), views, R, t


#: three cameras around the points: view 2's lines from views 0 and 1 cross steeply
AROUND = [(2.0, 0.0, -6.0), (0.0, 2.0, -6.0), (-2.0, 0.0, -6.0)]
#: three cameras on one line, looking the same way: every epipolar line runs along it, so the
#: lines of views 0 and 1 in view 2 are one line and place nothing
IN_A_LINE = [(-1.0, 0.0, -6.0), (0.0, 0.0, -6.0), (1.0, 0.0, -6.0)]


def _pairs(view_1_to_2_score):
    """Views 0-1 matched at 0.9 (tracks of two), views 1-2 at a lower score."""
    i = np.arange(N)
    rows, cols = np.r_[i, N + i], np.r_[N + i, 2 * N + i]
    return rows, cols, np.r_[np.full(N, 0.9), np.full(N, view_1_to_2_score)]


def _grown(geometry, score, planar_threshold):
    rows, cols, scores = _pairs(score)
    keep, track = verified_tracks(geometry, rows, cols, scores, 0.5, planar_threshold=planar_threshold)
    assert keep.all()
    return track


def test_a_keypoint_the_members_place_joins_their_track_at_the_point_to_point_threshold():
    _, geometry, *_ = _window(AROUND)
    track = _grown(geometry, 0.3, planar_threshold=0.2)
    assert (track[2 * N:] == track[:N]).all() and (track[:N] >= 0).all()  # tracks of three
    assert len(set(track.tolist())) == N


def test_below_the_point_to_point_threshold_or_without_it_nothing_joins():
    _, geometry, *_ = _window(AROUND)
    for score, planar_threshold in ((0.3, 0.4), (0.3, None), (0.1, 0.2)):
        track = _grown(geometry, score, planar_threshold)
        assert (track[2 * N:] < 0).all() and (track[:N] == track[N:2 * N]).all()


def test_a_keypoint_shifted_along_one_members_line_is_not_where_the_lines_cross():
    _, _, views, R, t = _window(AROUND)
    # view 2's keypoints slid 40 px along their epipolar lines from view 1: each agrees with
    # views 1-2 (its pair is kept) but lies far off the line from its view-0 member
    F12 = fundamental_from_poses(K, R[1], t[1], K, R[2], t[2])
    lines = homogeneous(views[1]) @ F12.T
    along = np.c_[lines[:, 1], -lines[:, 0]] / np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
    _, geometry, *_ = _window(AROUND, keypoints=views[2] + 40.0 * along)
    track = _grown(geometry, 0.3, planar_threshold=0.2)
    assert (track[2 * N:] < 0).all()


def test_lines_that_do_not_cross_place_nothing():
    _, geometry, *_ = _window(IN_A_LINE)
    track = _grown(geometry, 0.3, planar_threshold=0.2)
    assert (track[2 * N:] < 0).all() and (track[:N] >= 0).all()


def test_one_line_places_nothing():
    problem, geometry, *_ = _window(AROUND)
    del geometry.models[(0, 2)]  # view 2 verified against view 1 only: one line there
    geometry = WindowGeometry(problem, geometry.models)
    rows, cols, scores = _pairs(0.3)
    track = np.full(3 * N, -1, np.int64)
    track[:N] = track[N:2 * N] = np.arange(N)
    check = TrackCheck(geometry, rows[:N], cols[:N])
    assert (placed_members(geometry, track, rows, cols, scores, 0.2, 0.5, check) == track).all()


def test_pairs_of_keypoints_in_no_track_make_none():
    problem, geometry, *_ = _window(AROUND)
    rows, cols, _ = _pairs(0.3)
    scores = np.full(rows.shape[0], 0.3)  # every pair below the threshold: no track to grow
    keep, track = verified_tracks(geometry, rows, cols, scores, 0.5, planar_threshold=0.2)
    assert keep.all() and (track < 0).all()


def test_a_chained_model_places_nothing():
    # 30 points: the first 20 matched through all three views at 0.9 (their chains give view pair
    # 0-2 a chained model), the last 10 matched in views 0-1 at 0.9 and 1-2 at 0.3
    points = np.random.default_rng(2).uniform(-0.8, 0.8, (30, 3))
    n, last = len(points), np.arange(20, 30)
    problem, geometry, *_ = _window(AROUND, points=points)
    i = np.arange(n)
    rows, cols = np.r_[i, n + i], np.r_[n + i, 2 * n + i]
    scores = np.r_[np.full(n, 0.9), np.full(20, 0.9), np.full(10, 0.3)]
    _, track = verified_tracks(geometry, rows, cols, scores, 0.5, planar_threshold=0.2)
    assert (track[2 * n + last] == track[last]).all()  # the direct model of 0-2 places them
    del geometry.models[(0, 2)]
    geometry = WindowGeometry(problem, geometry.models)
    assert (0, 2) in geometry.with_chained_models(rows, cols, scores, 0.5).models
    _, track = verified_tracks(geometry, rows, cols, scores, 0.5, chained_models=True, planar_threshold=0.2)
    assert (track[:20] == track[2 * n:2 * n + 20]).all() and (track[:20] >= 0).all()
    assert (track[2 * n + last] < 0).all()  # one line of a direct model (from view 1) places nothing
