"""Tests of gcn_match_ros.rounding: greedy cycle-consistent tracks, relabelling, pairs, universe size."""
import numba
import numpy as np
import scipy.sparse as sp

from gcn_match_ros.rounding import (MergeTest, estimate_universe_size, greedy_tracks, is_cycle_consistent,
                                    relabel_tracks, track_members, tracks_to_pairs)

from conftest import (corrupted_pairs, graph_from_pairs, known_answer_problem as make_problem,
                      true_pair_list as true_pairs)


def test_greedy_tracks_never_puts_two_keypoints_of_one_view_together():
    view = np.array([0, 0, 1, 2])
    # 0-2 and 1-2 both strong: only the better one may join 2; 2-3 joins.
    track = greedy_tracks(4, view, np.array([0, 1, 2]), np.array([2, 2, 3]), np.array([0.9, 0.8, 0.7]))
    assert track[0] == track[2] == track[3] and track[1] == -1
    assert is_cycle_consistent(track, view)
    below = greedy_tracks(4, view, np.array([0]), np.array([2]), np.array([0.3]), threshold=0.5)
    assert np.all(below == -1)


@numba.njit
def _at_most_three(data, members, n_a, n_b):
    """A merge test that logs what it is asked: data = (log (calls, 6): the members, -1-padded,
    then n_a, n_b in the last two columns; calls (1,))."""
    log, calls = data
    log[calls[0], :n_a + n_b] = members
    log[calls[0], 4], log[calls[0], 5] = n_a, n_b
    calls[0] += 1
    return n_a + n_b <= 3


def test_greedy_tracks_asks_compatible_before_every_merge_with_the_members():
    view = np.array([0, 1, 2, 3])
    rows, cols, scores = np.array([0, 1, 2]), np.array([1, 2, 3]), np.array([0.9, 0.8, 0.7])
    log, calls = np.full((4, 6), -1), np.zeros(1, np.int64)
    track = greedy_tracks(4, view, rows, cols, scores, compatible=MergeTest(_at_most_three, (log, calls)))
    asked = [(sorted(r[:r[4]]), sorted(r[r[4]:r[4] + r[5]])) for r in log[:calls[0]].tolist()]
    assert asked == [([0], [1]), ([0, 1], [2]), ([0, 1, 2], [3])]
    assert track[0] == track[1] == track[2] and track[3] == -1


def test_relabel_and_pairs():
    np.testing.assert_array_equal(relabel_tracks([7, 7, 3, -1, 5, 5]), [0, 0, -1, -1, 1, 1])
    r, c = tracks_to_pairs(np.array([0, 1, 0, 0, -1]))
    assert sorted(zip(r.tolist(), c.tolist())) == [(0, 2), (0, 3), (2, 3)]


def test_estimate_universe_size_counts_points():
    prob = make_problem(4, 25, visibility=0.6, seed=3)
    adj = graph_from_pairs(prob, true_pairs(prob)).adjacency()
    n_points = np.unique(prob.gt_track[prob.gt_track >= 0]).size + int(np.sum(prob.gt_track == -1))
    assert estimate_universe_size(adj, prob.view_sizes) == n_points
    full = make_problem(3, 12, seed=0)
    assert estimate_universe_size(graph_from_pairs(full, true_pairs(full)).adjacency(), full.view_sizes) == 12
    # dropped and wrong edges do not change the number of points
    for seed in range(3):
        noisy = make_problem(5, 20, seed=seed)
        adj = graph_from_pairs(noisy, corrupted_pairs(noisy, 0.05, seed=seed)).adjacency()
        assert estimate_universe_size(adj, noisy.view_sizes) == 20
    # bounds: never below the largest view, never above max_rank
    assert estimate_universe_size(sp.csr_matrix((30, 30)), np.array([10, 10, 10])) == 30
    assert estimate_universe_size(sp.csr_matrix((30, 30)), np.array([10, 10, 10]), max_rank=12) == 12


def test_track_members_groups_keypoints_by_track_in_keypoint_order():
    members, starts = track_members(np.array([3, -1, 0, 3, 0, -1, 7]))
    assert members.tolist() == [2, 4, 0, 3, 6]   # track 0, then 3, then 7; ids without members skipped
    assert starts.tolist() == [0, 2, 4, 5]
    members, starts = track_members(np.full(4, -1))
    assert members.size == 0 and starts.tolist() == [0]


def test_the_plain_merge_can_be_compiled_ahead_of_the_first_window():
    """numba cannot cache the merge loop (it takes the merge test as an argument): the node's
    warm-up compiles the plain one, so a window that needs it first does not pay for it."""
    from gcn_match_ros.rounding import _merge_greedily, compile_plain_merge

    compile_plain_merge()
    assert any("_accept_every_merge" in str(sig) for sig in _merge_greedily.signatures)
