"""Tests of gcn_match_ros.metrics: pair counts, precision/recall, average precision, bootstrap."""
import math

import numpy as np
import pytest

from gcn_match_ros.metrics import average_precision, count_pairs, paired_bootstrap, reference_rows, score_result
from gcn_match_ros.problem import Problem, Result
from gcn_match_ros.rounding import tracks_to_pairs


def _problem(gt, views):
    views = np.asarray(views)
    offsets = np.r_[0, np.cumsum(np.bincount(views))]
    n = len(gt)
    return Problem(view_offsets=offsets, keypoints=np.zeros((n, 2)), descriptors=np.ones((n, 4)),
                   gt_track=gt)


# Two views of 3 keypoints + one of 2; gt: points 0,1 seen in all, -1 distractor, -2 unlabelled.
GT = [0, 1, -1, 1, 0, -2, 0, 1]


VIEWS = [0, 0, 0, 1, 1, 1, 2, 2]


def test_count_pairs_crafted():
    labelled, true = count_pairs(np.array(GT), np.array(VIEWS))
    # labelled keypoints: 7 (one -2) -> cross-view pairs: views sizes 3,2,2 -> 21 - 3 - 1 - 1 = 16
    assert labelled == 16
    assert true == 6  # each of points 0 and 1 seen in 3 views -> 3 pairs each


def test_perfect_and_partial_tracks():
    p = _problem(GT, VIEWS)
    perfect = Result(track=[0, 1, -1, 1, 0, -1, 0, 1], pair_rows=[], pair_cols=[], pair_scores=[])
    s = score_result(p, perfect)
    assert s["P"] == 1 and s["R"] == 1 and s["F1"] == 1
    # One wrong track {2 (distractor), 5 (unlabelled)}: unlabelled pairs are not scored.
    half = Result(track=[0, -1, 1, -1, 0, 1, -1, -1], pair_rows=[], pair_cols=[], pair_scores=[])
    s = score_result(p, half)
    assert s["P"] == 1.0 and s["R"] == pytest.approx(1 / 6)
    wrong = Result(track=[0, 1, -1, 0, 1, -1, -1, -1], pair_rows=[], pair_cols=[], pair_scores=[])
    assert score_result(p, wrong)["P"] == 0 and score_result(p, wrong)["F1"] == 0


def test_average_precision_closed_form():
    # Ranking: T, F, T with 2 more true pairs unlisted among 10 labelled pairs.
    ap = average_precision(np.array([0.9, 0.8, 0.7]), np.array([True, False, True]), n_true=4, n_pairs=10)
    # steps: R .25 P 1; R .5 P 2/3; then the score-0 group: R 1, P 4/10
    assert ap == pytest.approx(0.25 * 1 + 0.25 * 2 / 3 + 0.5 * 0.4)
    # Ties form one step.
    tie = average_precision(np.array([0.5, 0.5]), np.array([True, False]), n_true=1, n_pairs=2)
    assert tie == pytest.approx(0.5)
    assert math.isnan(average_precision(np.zeros(0), np.zeros(0, bool), 0, 3))


def test_similarity_and_paper_l1_with_reference_rows():
    # p points in v views, all visible: identity L1 = (v-1)/(v p), all-zero = 1/p (evaluation.md).
    v, pts = 3, 80
    gt = np.tile(np.arange(pts), v)
    p = _problem(gt, np.repeat(np.arange(v), pts))
    rows = reference_rows(p)
    assert rows["identity"]["L1"] == pytest.approx((v - 1) / (v * pts))
    assert rows["all-zero"]["L1"] == pytest.approx(1 / pts)
    assert rows["identity"]["F1"] == 0
    # Perfect soft scores: L1 = 0, same-point similarity 1, different-point 0.
    r, c = tracks_to_pairs(gt)
    perfect = Result(track=gt, pair_rows=r, pair_cols=c, pair_scores=np.ones(r.size))
    s = score_result(p, perfect)
    assert s["L1"] == 0 and s["same_sim"] == 1 and s["diff_sim"] == 0 and s["AP"] == pytest.approx(1)


def test_paired_bootstrap():
    a = np.array([0.8, 0.7, 0.9, 0.6])
    mean, lo, hi = paired_bootstrap(a, a - 0.05)
    np.testing.assert_allclose([mean, lo, hi], 0.05)  # a constant difference has no spread
    mean, lo, hi = paired_bootstrap([1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0], resamples=4000)
    assert mean == 0.0 and -1.0 <= lo < -0.4 and 0.4 < hi <= 1.0
    assert paired_bootstrap(a, a[::-1], seed=3) == paired_bootstrap(a, a[::-1], seed=3)
    with pytest.raises(ValueError, match="equally long"):
        paired_bootstrap(a, a[:3])
