"""Tests of gcn_match_ros.edges.duplicates and of verified_tracks in one-plane windows: known answers."""
import numpy as np

from gcn_match_ros.edges.consistency import WindowGeometry, verified_tracks
from gcn_match_ros.edges.duplicates import DUPLICATE_PX, KEY_STEP, better_placed_members, merge_order
from gcn_match_ros.edges.verify import PairModel
from gcn_match_ros.problem import Problem

SHIFT = np.array([100.0, 3.0])
H = np.array([[1.0, 0, SHIFT[0]], [0, 1.0, SHIFT[1]], [0, 0, 1.0]])
F = np.array([[0.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # a pure x translation: horizontal lines


def _window(xa, xb):
    n_a, n_b = len(xa), len(xb)
    return Problem(view_offsets=np.array([0, n_a, n_a + n_b]), keypoints=np.concatenate([xa, xb]).astype(np.float32),
                   descriptors=np.zeros((n_a + n_b, 8), np.float32))


def _points():
    """Four points of view a; view b holds their true images, and after them a near-duplicate of
    the first image 1.5 px off and a keypoint 5 px off the second (no duplicate: too far)."""
    xa = np.array([[10.0, 10], [60, 10], [10, 60], [60, 60]])
    xb = np.r_[xa + SHIFT, xa[:1] + SHIFT + [1.5, 0.0], xa[1:2] + SHIFT + [5.0, 0.0]]
    return xa, xb


def _geometry(problem, planar=True):
    model = (PairModel(H=H, F=None, planar=True, seeds=4, inliers_h=4, px=10.0) if planar
             else PairModel(H=None, F=F, planar=False, seeds=4, inliers_f=4, epipolar_px=10.0))
    return WindowGeometry(problem, {(0, 1): model})


def _plane_window(xa, xb, px=3.0):
    """Views a, b and a third view of the plane, each padded with far keypoints to the size a
    model needs, every view pair verified by its homography: a one-plane window. Returns the
    geometry and the offset of view b."""
    filler = np.c_[np.arange(12) * 20.0 + 400.0, np.full(12, 400.0)]
    views = [np.r_[xa, filler], np.r_[xb, filler + SHIFT], np.r_[xa, filler] + 2 * SHIFT]
    sizes = [len(v) for v in views]
    problem = Problem(view_offsets=np.r_[0, np.cumsum(sizes)], keypoints=np.concatenate(views).astype(np.float32),
                      descriptors=np.zeros((sum(sizes), 8), np.float32))
    models = {(0, 1): H, (0, 2): H @ H, (1, 2): H}
    geometry = WindowGeometry(problem, {k: PairModel(H=Hk, F=None, planar=True, seeds=12, inliers_h=12, px=px)
                                        for k, Hk in models.items()})
    assert geometry.one_plane
    return geometry, sizes[0]


def test_verified_tracks_takes_the_better_placed_duplicate_only_when_asked():
    xa, xb = _points()
    geometry, b = _plane_window(xa, xb)
    rows, cols = np.array([0, 0]), b + np.array([0, 4])
    scores = np.array([0.7, 0.8])  # the duplicate scores higher: merged first without the rule
    keep, track = verified_tracks(geometry, rows, cols, scores, 0.5)
    assert keep.all() and track[0] == track[b + 4] and track[b] == -1
    keep, track = verified_tracks(geometry, rows, cols, scores, 0.5, prefer_localised=True)
    # both pairs stay published; the track takes the better-placed keypoint
    assert keep.all() and track[0] == track[b] and track[b + 4] == -1
    # two views only: not one plane (a homography also fits a 3-D scene seen with little
    # parallax), the merge decides as scored
    problem = _window(np.r_[xa, np.zeros((12, 2)) + 500], np.r_[xb, np.zeros((12, 2)) + 600])
    two = WindowGeometry(problem, {(0, 1): PairModel(H=H, F=None, planar=True, seeds=12, inliers_h=12, px=3.0)})
    assert not two.one_plane
    _, track = verified_tracks(two, rows, cols, scores, 0.5, prefer_localised=True)
    assert track[0] >= 0 and track[0] == track[b + 4] and track[b] == -1


def test_two_tracks_exchange_near_duplicates_the_homography_places_the_other_way_round():
    xa, xb = _points()
    # the true image of point 0 went to point 2 (a wrong pair the huge tolerance lets agree),
    # point 0 to its duplicate: exchanged, both tracks keep their size
    geometry, b = _plane_window(xa, xb, px=100.0)
    rows, cols = np.array([2, 0]), b + np.array([0, 4])
    _, before = verified_tracks(geometry, rows, cols, np.array([0.99, 0.8]), 0.5)
    assert before[2] == before[b] and before[0] == before[b + 4]
    _, track = verified_tracks(geometry, rows, cols, np.array([0.99, 0.8]), 0.5, prefer_localised=True)
    assert track[0] == track[b] == before[0] and track[2] == track[b + 4] == before[2]


def test_a_track_swaps_a_member_for_the_better_placed_free_duplicate():
    """Three views of a plane, each the one before shifted by SHIFT. Point 0's track holds in view
    1 the near-duplicate 1.5 px off (joined through view 2, say); its true image is in no track."""
    xa, xb = _points()
    xc = xa + 2 * SHIFT
    n_a, n_b = len(xa), len(xb)
    problem = Problem(view_offsets=np.array([0, n_a, n_a + n_b, n_a + n_b + n_a]),
                      keypoints=np.concatenate([xa, xb, xc]).astype(np.float32),
                      descriptors=np.zeros((2 * n_a + n_b, 8), np.float32))
    H2 = H @ H
    models = {(0, 1): PairModel(H=H, F=None, planar=True, seeds=4, inliers_h=4, px=3.0),
              (0, 2): PairModel(H=H2, F=None, planar=True, seeds=4, inliers_h=4, px=3.0),
              (1, 2): PairModel(H=H, F=None, planar=True, seeds=4, inliers_h=4, px=3.0)}
    track = np.full(problem.n_keypoints, -1)
    track[[0, n_a + 4, n_a + n_b]] = 0       # point 0: the duplicate in view 1
    track[[1, n_a + 1, n_a + n_b + 1]] = 1   # point 1: right, and its 5 px rival is no duplicate
    swapped = better_placed_members(WindowGeometry(problem, models), track)
    expected = track.copy()
    expected[n_a + 4], expected[n_a] = -1, 0
    np.testing.assert_array_equal(swapped, expected)
    assert DUPLICATE_PX < 5.0
    # an epipolar model in the track: nothing ranks the duplicates, nothing changes
    models[(1, 2)] = PairModel(H=None, F=F, planar=False, seeds=4, inliers_f=4, epipolar_px=10.0)
    np.testing.assert_array_equal(better_placed_members(WindowGeometry(problem, models), track), track)
    # a duplicate already in another track is not taken
    track[[n_a, n_a + n_b + 2]] = 2
    models[(1, 2)] = PairModel(H=H, F=None, planar=True, seeds=4, inliers_h=4, px=3.0)
    np.testing.assert_array_equal(better_placed_members(WindowGeometry(problem, models), track), track)


def test_the_duplicate_the_homography_places_better_is_merged_first():
    xa, xb = _points()
    problem = _window(xa, xb)
    n_a = len(xa)
    # 0 -> its true image, 0 -> its duplicate (1.5 px off), 1 -> its true image, 1 -> 5 px off
    rows = np.array([0, 0, 1, 1])
    cols = n_a + np.array([0, 4, 1, 5])
    scores = np.array([0.5, 0.8, 0.9, 0.95])
    keys = merge_order(_geometry(problem), rows, cols, scores, np.ones(4, bool))
    np.testing.assert_array_equal(keys, [0.8 + KEY_STEP, 0.8, 0.9, 0.95])
    # either order of a pair's keypoints; only candidates compete
    np.testing.assert_array_equal(merge_order(_geometry(problem), cols, rows, scores, np.ones(4, bool)), keys)
    np.testing.assert_array_equal(merge_order(_geometry(problem), rows, cols, scores,
                                              np.array([False, True, True, True])), scores)
    # a larger duplicate radius makes the 5 px keypoint a near-duplicate of the true image too
    keys = merge_order(_geometry(problem), rows, cols, scores, np.ones(4, bool), duplicate_px=6.0)
    np.testing.assert_array_equal(keys, [0.8 + KEY_STEP, 0.8, 0.95 + KEY_STEP, 0.95])
    # an epipolar model does not rank them
    np.testing.assert_array_equal(merge_order(_geometry(problem, planar=False), rows, cols, scores,
                                              np.ones(4, bool)), scores)


def _three_views(models_planar=(True, True, True)):
    """A plane seen three times, 16 points a view (enough for a model: verify.MIN_SEEDS)."""
    xa = np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(-1, 2) * 40.0 + 10.0
    problem = Problem(view_offsets=np.array([0, 16, 32, 48]),
                      keypoints=np.concatenate([xa, xa + SHIFT, xa + 2 * SHIFT]).astype(np.float32),
                      descriptors=np.zeros((48, 8), np.float32))
    Hs = {(0, 1): H, (0, 2): H @ H, (1, 2): H}
    models = {k: (PairModel(H=Hk, F=None, planar=True, seeds=4, inliers_h=4, px=3.0) if p
                  else PairModel(H=None, F=F, planar=False, seeds=4, inliers_f=4, epipolar_px=10.0))
              for (k, Hk), p in zip(Hs.items(), models_planar)}
    return problem, models


def test_one_plane_needs_every_view_pair_verified_by_a_homography():
    problem, models = _three_views()
    assert WindowGeometry(problem, models).one_plane
    assert not WindowGeometry(problem, {k: m for k, m in models.items() if k != (1, 2)}).one_plane  # unverified
    assert not WindowGeometry(problem, _three_views((True, True, False))[1]).one_plane  # an epipolar model
    assert not WindowGeometry(problem, {}).one_plane
    # two of the three views too small for a model: fewer than three views to judge by
    small = Problem(view_offsets=np.array([0, 16, 20, 24]), keypoints=problem.keypoints[:24],
                    descriptors=problem.descriptors[:24])
    assert not WindowGeometry(small, {(0, 1): models[(0, 1)]}).one_plane


def test_the_planar_threshold_applies_in_one_plane_windows_only():
    rows = np.array([0, 1, 2, 3])
    cols = rows + 16
    scores = np.array([0.9, 0.4, 0.4, 0.2])
    joined = lambda track: [bool(track[r] >= 0 and track[r] == track[c]) for r, c in zip(rows, cols)]  # noqa: E731
    problem, models = _three_views()
    _, track = verified_tracks(WindowGeometry(problem, models), rows, cols, scores, 0.5, planar_threshold=0.3)
    assert joined(track) == [True, True, True, False]
    _, track = verified_tracks(WindowGeometry(problem, models), rows, cols, scores, 0.5)
    assert joined(track) == [True, False, False, False]
    # view pair (1, 2) epipolar: the window is not one plane, the precision-first threshold holds
    problem, models = _three_views((True, True, False))
    _, track = verified_tracks(WindowGeometry(problem, models), rows, cols, scores, 0.5, planar_threshold=0.3)
    assert joined(track) == [True, False, False, False]


def test_pairs_of_a_view_too_small_to_check_keep_the_precision_first_threshold():
    """A fourth view of 4 keypoints (fewer than a model needs) in a one-plane window: its pairs
    are kept as scored, not checked point to point, so they merge at the threshold, not the
    planar one."""
    problem, models = _three_views()
    xa = problem.keypoints[:4]
    four = Problem(view_offsets=np.array([0, 16, 32, 48, 52]),
                   keypoints=np.concatenate([problem.keypoints, xa + 3 * SHIFT]).astype(np.float32),
                   descriptors=np.zeros((52, 8), np.float32))
    geometry = WindowGeometry(four, models)
    assert geometry.one_plane and geometry.small[3]
    rows, cols = np.array([1, 2]), np.array([17, 49])  # view 0 -> view 1 (checked), view 0 -> view 3
    _, track = verified_tracks(geometry, rows, cols, np.array([0.4, 0.4]), 0.5, planar_threshold=0.3)
    assert track[1] == track[17] >= 0 and track[49] == -1
