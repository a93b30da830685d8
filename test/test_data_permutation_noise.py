"""Tests of gcn_match_ros.data.permutation_noise: the paper's permutation protocol and its noisy graphs."""
import numpy as np
import pytest

from gcn_match_ros.data.permutation_noise import PAPER_SYNTHETIC_ROWS, graph_outlier_rate, permutation_noise_problem

from conftest import same_problem as _same, true_pair_set as _true_pairs


def _check_graph_form(g, prob):
    assert g.rows.dtype == np.int64 and g.cols.dtype == np.int64 and g.rank.dtype == np.int64
    assert g.weights.dtype == np.float32 and g.cosine.dtype == np.float32 and g.ratio.dtype == np.float32
    order = np.lexsort((g.cols, g.rows))
    assert np.array_equal(order, np.arange(g.n_edges))  # sorted by (row, col)
    view = prob.view_index
    assert np.all(view[g.rows] != view[g.cols])  # cross-view only
    A = g.adjacency()
    assert abs(A - A.T).max() == 0  # symmetric, both directions stored
    assert np.all((g.weights > 0) & (g.weights <= 1))
    d = prob.descriptors / np.linalg.norm(prob.descriptors, axis=1, keepdims=True)
    np.testing.assert_allclose(g.cosine, np.sum(d[g.rows] * d[g.cols], axis=1), atol=1e-5)
    assert np.all(g.ratio == 1) and np.all(g.rank == 0)


def test_permutation_exact_graph_is_the_truth():
    prob, g = permutation_noise_problem(4, n_perms=0, outlier_transpositions=0, rng=3)
    _check_graph_form(g, prob)
    r, c, pos = g.upper_pairs()
    assert set(zip(r.tolist(), c.tolist())) == _true_pairs(prob.gt_track, prob.view_index)
    assert np.all(g.weights == 1.0)
    assert prob.descriptors.shape == (100, 12) and np.all(prob.view_sizes == 25)
    assert sorted(prob.gt_track[prob.view_slice(2)]) == list(range(25))
    assert graph_outlier_rate(g, prob.gt_track) == 0.0


def test_permutation_deterministic():
    a, ga = permutation_noise_problem(3, n_perms=3, outlier_transpositions=1, rng=5)
    b, gb = permutation_noise_problem(3, n_perms=3, outlier_transpositions=1, rng=5)
    assert _same(a, b)
    for k in ("rows", "cols", "weights", "cosine"):
        assert np.array_equal(getattr(ga, k), getattr(gb, k))


def test_permutation_noise_block_structure():
    prob, g = permutation_noise_problem(3, n_perms=3, rng=4)
    _check_graph_form(g, prob)
    gt = prob.gt_track
    true = gt[g.rows] == gt[g.cols]
    assert np.all(g.weights[true] >= 0.9 - 1e-6)  # 0.9·I (+ 0.1 where a permutation hits the diagonal)
    assert np.all(g.weights[~true] <= 0.3 + 1e-6)  # noise entries 0.1 × hits (3 perms)
    # every true pair is present, and each keypoint has ~K noisy edges per other view
    r, c, _ = g.upper_pairs()
    assert _true_pairs(gt, prob.view_index) <= set(zip(r.tolist(), c.tolist()))
    assert graph_outlier_rate(g, gt) == 0.0  # noise edges are weak (< 0.5), not matches


def test_permutation_outlier_rate():
    # one transposition per view pair: exactly 2 of the 25 matches of every block are wrong
    for s in range(5):
        prob, g = permutation_noise_problem(3, outlier_transpositions=1, rng=s)
        assert graph_outlier_rate(g, prob.gt_track) == pytest.approx(2 / 25)
        r, c, pos = g.upper_pairs()
        assert r.size == 3 * 25
    # the paper's "5%" and "10%" rows: ~6% and ~8% wrong matches on average
    for row, want in (("outliers_5pct", 0.06), ("outliers_10pct", 0.08)):
        rates = [graph_outlier_rate(g, p.gt_track)
                 for p, g in (permutation_noise_problem(3, rng=s, **PAPER_SYNTHETIC_ROWS[row]) for s in range(150))]
        assert abs(np.mean(rates) - want) < 0.01
        assert 0.05 <= np.mean(rates) <= 0.09


def test_permutation_descriptors_like_paper_baseline():
    same = []
    for s in range(20):
        prob, _ = permutation_noise_problem(3, rng=s)
        d, gt, view = prob.descriptors, prob.gt_track, prob.view_index
        S = d @ d.T
        m = (view[:, None] != view[None, :]) & (gt[:, None] == gt[None, :])
        same.append(S[m].mean())
    assert 0.45 < np.mean(same) < 0.57  # the paper's "Initialization Baseline": 0.511
