"""Tests of gcn_match_ros.view_pairs: grouping pairs by view pair, known answers."""
import numpy as np

from gcn_match_ros.view_pairs import by_view_pair, in_view_order


def test_groups_equal_the_masks_in_ascending_order():
    va = np.array([0, 1, 0, 0, 2, 1, 0])
    vb = np.array([1, 2, 2, 1, 3, 2, 1])
    groups = by_view_pair(va, vb)
    assert list(groups) == [(0, 1), (0, 2), (1, 2), (2, 3)]
    np.testing.assert_array_equal(groups[(0, 1)], [0, 3, 6])
    np.testing.assert_array_equal(groups[(0, 2)], [2])
    np.testing.assert_array_equal(groups[(1, 2)], [1, 5])
    np.testing.assert_array_equal(groups[(2, 3)], [4])
    rng = np.random.default_rng(0)
    va, vb = rng.integers(0, 9, 500), rng.integers(0, 9, 500)
    for (a, b), sel in by_view_pair(va, vb).items():
        np.testing.assert_array_equal(sel, np.flatnonzero((va == a) & (vb == b)))


def test_no_pairs_no_groups():
    assert by_view_pair(np.zeros(0, np.int64), np.zeros(0, np.int64)) == {}


def test_in_view_order_puts_the_lower_views_keypoint_first():
    view_index = np.array([0, 0, 1, 1, 2])
    rows, cols, va, vb = in_view_order(view_index, np.array([2, 0, 4]), np.array([1, 3, 2]))
    assert rows.tolist() == [1, 0, 2] and cols.tolist() == [2, 3, 4]
    assert va.tolist() == [0, 0, 1] and vb.tolist() == [1, 1, 2]
