"""Tests of gcn_match_ros.edges.ambiguity: Lowe's ratio along the epipolar line, known answers."""
import numpy as np
import pytest
import torch

from gcn_match_ros.descriptors import cosine_distance
from gcn_match_ros.edges.ambiguity import BAND_PX, MIN_JUDGED_COSINE, ambiguous_pairs, band_runner_up, near_copies
from gcn_match_ros.edges.consistency import WindowGeometry
from gcn_match_ros.edges.verify import PairModel
from gcn_match_ros.problem import Problem

# cameras side by side (pure x translation): the epipolar line of (x, y) is the row y in the
# other view, so "within BAND_PX of the line" means |y_b - y_a| <= BAND_PX
F_ROWS = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class _Blocks:
    """The one method of DescriptorSimilarity that ambiguous_pairs reads."""

    def __init__(self, blocks):
        self.blocks = blocks

    def block(self, a, b, normalization):
        return torch.from_numpy(self.blocks[(a, b)])


def _geometry(xa, xb, models):
    """A window of the two views (descriptors unused: the cosines come from _Blocks)."""
    problem = Problem(view_offsets=np.array([0, len(xa), len(xa) + len(xb)]), keypoints=np.concatenate([xa, xb]),
                      descriptors=np.zeros((len(xa) + len(xb), 8), np.float32))
    return WindowGeometry(problem, models)


def _scene():
    xa = np.array([[10.0, 50.0], [70.0, 52.0], [300.0, 200.0]])
    xb = np.array([[20.0, 50.0], [40.0, 51.0], [40.0, 60.0], [90.0, 200.0]])
    sim = np.array([[0.90, 0.85, 0.99, 0.10],    # a0: partner b0, a rival b1 on its row, b2 off it
                    [0.30, 0.20, 0.20, 0.20],    # a1: on b0's row in view a
                    [0.10, 0.10, 0.10, 0.95]], np.float32)  # a2 <-> b3: alone on their rows
    return xa, xb, sim


def test_the_runner_up_is_the_best_other_keypoint_on_either_line():
    xa, xb, sim = _scene()
    got = band_runner_up(F_ROWS, xa, xb, sim, np.array([0, 2, 1]), np.array([0, 3, 0]))
    # (a0, b0): b1 on a0's row (0.85) beats a1 on b0's row (0.30); b2 (0.99) is 10 px off the line
    # (a2, b3): nobody else on rows 200; (a1, b0): a0 on b0's row, cosine 0.90 with b0
    np.testing.assert_allclose(got, [0.85, -np.inf, 0.90])


def test_band_edge_and_the_partner_itself_are_handled():
    xa = np.array([[0.0, 0.0]])
    xb = np.array([[5.0, 0.0], [9.0, BAND_PX], [9.0, BAND_PX + 0.01]])
    sim = np.array([[0.9, 0.5, 0.8]], np.float32)
    assert band_runner_up(F_ROWS, xa, xb, sim, np.array([0]), np.array([0]))[0] == pytest.approx(0.5)
    # the partner is never its own rival: only it on the line -> none
    assert band_runner_up(F_ROWS, xa, xb[:1], sim[:, :1], np.array([0]), np.array([0]))[0] == -np.inf


def test_a_pair_is_ambiguous_when_its_rival_is_nearly_as_similar():
    xa, xb, sim = _scene()
    geometry = _geometry(xa, xb, {(0, 1): PairModel(H=None, F=F_ROWS)})
    rows, cols = np.array([0, 2]), np.array([3, 6])            # (a0, b0) and (a2, b3)
    ratio_at = cosine_distance(np.float64(np.float32(0.90))) / cosine_distance(np.float64(np.float32(0.85)))  # ~0.816
    got = ambiguous_pairs(geometry, _Blocks({(0, 1): sim}), "l2", rows, cols, ratio=0.8)
    np.testing.assert_array_equal(got, [True, False])          # a lone pair has no rival
    got = ambiguous_pairs(geometry, _Blocks({(0, 1): sim}), "l2", rows, cols, ratio=ratio_at + 1e-6)
    np.testing.assert_array_equal(got, [False, False])
    # a partner beaten on its own line is ambiguous at any ratio up to 1
    beaten = sim.copy()
    beaten[0, 1] = 0.95
    got = ambiguous_pairs(geometry, _Blocks({(0, 1): beaten}), "l2", rows, cols, ratio=1.0)
    np.testing.assert_array_equal(got, [True, False])


def test_planar_missing_and_absent_models_judge_nothing():
    xa, xb, sim = _scene()
    rows, cols = np.array([0]), np.array([3])
    blocks = _Blocks({(0, 1): sim})
    for models in ({(0, 1): PairModel(H=np.eye(3), F=F_ROWS, planar=True)}, {(0, 1): None}, {}):
        assert not ambiguous_pairs(_geometry(xa, xb, models), blocks, "l2", rows, cols, ratio=0.5).any()
    assert ambiguous_pairs(_geometry(xa, xb, {(0, 1): PairModel(H=None, F=F_ROWS)}), blocks, "l2",
                           np.zeros(0, np.int64), np.zeros(0, np.int64), ratio=0.8).shape == (0,)


def test_pairs_less_similar_than_the_judged_cosine_are_not_judged():
    """A near-copy rival makes a pair ambiguous only when the pair itself is a strong match: the
    same rival ratio with cosines of weak descriptors (below MIN_JUDGED_COSINE) is left alone."""
    xa, xb = np.array([[10.0, 50.0]]), np.array([[20.0, 50.0], [40.0, 51.0]])
    geometry = _geometry(xa, xb, {(0, 1): PairModel(H=None, F=F_ROWS)})
    rows, cols = np.array([0]), np.array([1])
    for own, rival, judged in ((MIN_JUDGED_COSINE, MIN_JUDGED_COSINE - 0.01, True),
                               (MIN_JUDGED_COSINE - 0.01, MIN_JUDGED_COSINE - 0.02, False)):
        sim = np.array([[own, rival]], np.float32)
        assert cosine_distance(np.float64(own)) >= 0.9 * cosine_distance(np.float64(rival))  # a rival either way
        got = ambiguous_pairs(geometry, _Blocks({(0, 1): sim}), "l2", rows, cols, ratio=0.9)
        np.testing.assert_array_equal(got, [judged])


def test_near_copies_are_the_pairs_at_or_above_the_judged_cosine_in_either_order():
    xa, xb, sim = _scene()
    geometry = _geometry(xa, xb, {})  # no model needed: any view pair is read
    sim = sim.copy()
    sim[1, 0] = MIN_JUDGED_COSINE  # exactly at the bar: a near-copy
    rows, cols = np.array([0, 1, 2, 3 + 3]), np.array([3 + 0, 3 + 0, 3 + 1, 2])  # last one written (b, a)
    got = near_copies(geometry, _Blocks({(0, 1): sim}), "l2", rows, cols)
    np.testing.assert_array_equal(got, [True, True, False, True])
