"""Tests of gcn_match_ros.edges.neighbourhood: neighbourhood consensus, known answers."""
import numpy as np
import pytest

from gcn_match_ros.edges.consistency import WindowGeometry, verified_tracks
from gcn_match_ros.edges.neighbourhood import check_neighbourhood, followed_pairs, shared_neighbours
from gcn_match_ros.edges.verify import PairModel
from gcn_match_ros.problem import Problem


def _grid(n_side=6, step=40.0):
    """A facade of n_side x n_side points seen by two cameras: view b is view a shifted by (100, 3)."""
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side)), -1).reshape(-1, 2) * step
    return g + 20.0, g + [120.0, 23.0]


def test_a_line_of_four_with_k_two_counts_the_neighbours_kept_in_both_views():
    xa = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [30.0, 0.0]])
    # pair 3's partner sits beside pair 0's: in b its nearest are pairs 0 and 1 (by distance), in a 2 and 1
    xb = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0], [-5.0, 0.0]])
    shared = shared_neighbours(xa, xb, np.ones(4, bool), k=2)
    # pair 0: a {1, 2}, b {3, 1} -> 1; pair 1: a {0, 2}, b {0, 2} -> 2 (|1-3|=15 in b, farther than 0 and 2);
    # pair 2: a {1, 3}, b {1, 0} -> 1; pair 3: a {2, 1}, b {0, 1} -> 1
    np.testing.assert_array_equal(shared, [1, 2, 1, 1])


def test_a_match_shifted_to_a_repetition_shares_no_neighbour():
    xa, xb = _grid()
    wrong = xb.copy()
    wrong[0] = xb[35]  # corner (0, 0) matched to the opposite corner's copy (the same window's twin)
    shared = shared_neighbours(xa, wrong, np.ones(len(xa), bool), k=8)
    assert shared[0] == 0
    assert shared[1:].min() >= 6  # the others keep most of theirs (one lost the shifted pair)
    # unchanged layout: everyone keeps its neighbours except where ties order them differently
    assert shared_neighbours(xa, xb, np.ones(len(xa), bool), k=8).min() >= 6


def test_pairs_that_are_not_references_are_judged_against_the_references():
    xa, xb = _grid()
    ref = np.ones(len(xa), bool)
    ref[[0, 7]] = False
    wrong = xb.copy()
    wrong[0] = xb[35]
    shared = shared_neighbours(xa, wrong, ref, k=8)
    assert shared[0] == 0 and shared[7] >= 6


def test_counts_only_for_the_judged_pairs_are_those_of_all():
    xa, xb = _grid()
    wrong = xb.copy()
    wrong[0] = xb[35]
    ref = np.ones(len(xa), bool)
    ref[7] = False
    judged = np.zeros(len(xa), bool)
    judged[[0, 7, 20]] = True
    every = shared_neighbours(xa, wrong, ref, k=8)
    some = shared_neighbours(xa, wrong, ref, k=8, judged=judged)
    np.testing.assert_array_equal(some[judged], every[judged])
    assert (some[~judged] == 8).all() and some[0] == 0


def test_too_few_references_judge_nothing():
    xa, xb = _grid(3)  # 9 pairs
    wrong = xb.copy()
    wrong[0] = xb[8]
    np.testing.assert_array_equal(shared_neighbours(xa, wrong, np.ones(9, bool), k=8), np.full(9, 8))
    assert shared_neighbours(xa, wrong, np.ones(9, bool), k=0).tolist() == [0] * 9


def _window(xa, xb):
    n = len(xa)
    return Problem(view_offsets=np.array([0, n, 2 * n]), keypoints=np.concatenate([xa, xb]).astype(np.float32),
                   descriptors=np.zeros((2 * n, 8), np.float32))


def test_followed_pairs_judges_per_view_pair_and_only_the_judged():
    xa, xb = _grid()
    n = len(xa)
    problem = _window(xa, xb)
    rows, cols = np.arange(n), np.arange(n) + n
    cols[0] = 35 + n  # the shifted pair
    judged = np.ones(n, bool)
    keep = followed_pairs(problem.keypoints, problem.view_index, rows, cols, judged, judged, k=8, min_shared=2)
    assert not keep[0] and keep[1:].all()
    judged[0] = False
    keep = followed_pairs(problem.keypoints, problem.view_index, rows, cols, judged, judged, k=8, min_shared=2)
    assert keep.all()
    # the pair written (b, a) is the same pair
    keep = followed_pairs(problem.keypoints, problem.view_index, cols, rows, np.ones(n, bool), np.ones(n, bool))
    assert not keep[0] and keep[1:].all()


def test_verified_tracks_drops_the_shifted_pair_only_when_asked():
    xa, xb = _grid()
    n = len(xa)
    problem = _window(xa, xb)
    # a homography that explains every pair, the shifted one too (a repetition on the model's locus)
    H = np.array([[1.0, 0, 100.0], [0, 1.0, 3.0], [0, 0, 1.0]])
    geometry = WindowGeometry(problem, {(0, 1): PairModel(H=H, F=None, planar=True, seeds=n, inliers_h=n, px=1e6)})
    rows, cols = np.arange(n), np.arange(n) + n
    cols[0] = 35 + n
    scores = np.full(n, 0.9)
    keep, _ = verified_tracks(geometry, rows, cols, scores, 0.5)
    assert keep.all()
    keep, track = verified_tracks(geometry, rows, cols, scores, 0.5, neighbours=8, min_shared=2)
    assert not keep[0] and keep[1:].all()
    # keypoint 0 of view a is left alone; its would-be partner goes with its own twin
    assert track[0] == -1 and track[35] == track[35 + n] and track[1] == track[1 + n]


@pytest.mark.parametrize("k, min_shared", [(-1, 0), (8, 9), (8, -1)])
def test_bad_settings_are_refused(k, min_shared):
    with pytest.raises(ValueError, match="neighbourhood"):
        check_neighbourhood(k, min_shared)


def test_off_takes_any_min_shared():
    check_neighbourhood(0, 2)
