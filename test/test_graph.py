"""The correspondence graph (gcn_match_ros.graph): candidates, symmetry, linear size."""
import numpy as np
import pytest

from gcn_match_ros.descriptors import normalize_descriptors
from gcn_match_ros.graph import GraphConfig, _taken, build_graph
from gcn_match_ros.problem import Problem

from conftest import permuted_views_problem


def _dense_reference(problem, k):
    """The paper's construction with dense matrices, for comparison on small problems."""
    d = normalize_descriptors(problem.descriptors)
    s = d @ d.T
    view = problem.view_index
    cross = view[:, None] != view[None, :]
    lo, hi = s[cross].min(), s[cross].max()
    s = (s - lo) / (hi - lo)
    a = np.zeros_like(s)
    offs = problem.view_offsets
    for i in range(problem.n_views):
        for j in range(problem.n_views):
            if i == j:
                continue
            blk = s[offs[i]:offs[i + 1], offs[j]:offs[j + 1]]
            top = np.argsort(-blk, axis=1)[:, :k]
            for r, cs in enumerate(top):
                a[offs[i] + r, offs[j] + cs] = blk[r, cs]
    return np.maximum(a, a.T)


@pytest.mark.parametrize("k", [1, 2, 4])
def test_paper_graph_matches_dense_construction(k):
    p = permuted_views_problem(n_views=4, n_points=9, noise=0.8, seed=3)
    g = build_graph(p, GraphConfig.paper(k))
    np.testing.assert_allclose(g.adjacency().toarray(), _dense_reference(p, k), atol=1e-6)


def test_graph_is_symmetric_cross_view_and_sorted():
    p = permuted_views_problem(n_views=3, n_points=10, noise=0.5)
    g = build_graph(p)
    a = g.adjacency().toarray()
    np.testing.assert_array_equal(a, a.T)
    view = p.view_index
    assert np.all(view[g.rows] != view[g.cols])
    assert np.all(np.diff(g.rows * g.n_nodes + g.cols) > 0)
    assert g.weights.min() >= 0 and g.weights.max() <= 1


def test_mutual_nn_on_noiseless_views_gives_exactly_the_true_pairs():
    p = permuted_views_problem(n_views=3, n_points=15)
    g = build_graph(p, GraphConfig.mutual_nn())
    r, c, _ = g.upper_pairs()
    assert np.all(p.gt_track[r] == p.gt_track[c])
    assert r.size == 3 * 15
    assert np.all(g.weights == 1)


def test_ratio_test_and_floor_select_subsets():
    p = permuted_views_problem(n_views=3, n_points=30, noise=1.0, seed=1)
    full = build_graph(p, GraphConfig(k=1, mutual=True))
    ratio = build_graph(p, GraphConfig(k=1, mutual=True, ratio=0.7))
    floor = build_graph(p, GraphConfig(k=1, mutual=True, min_similarity=0.8))
    key = lambda g: set(zip(g.rows.tolist(), g.cols.tolist()))  # noqa: E731
    assert key(ratio) < key(full) and key(floor) <= key(full)
    assert np.all(ratio.ratio < 0.7)


def test_empty_views_and_single_keypoints():
    p = Problem(view_offsets=[0, 0, 1, 3], keypoints=np.zeros((3, 2)), descriptors=np.eye(3, 4))
    g = build_graph(p)
    assert g.n_nodes == 3 and np.all(p.view_index[g.rows] != p.view_index[g.cols])
    single = Problem(view_offsets=[0, 2], keypoints=np.zeros((2, 2)), descriptors=np.eye(2))
    assert build_graph(single).n_edges == 0


def test_a_pair_proposed_from_both_ends_is_one_entry_each_way_with_the_lower_ratio_and_rank():
    from gcn_match_ros.graph import _merged_both_ways

    # proposals 0 -> 2 and 2 -> 0 (the same pair from both ends), 1 -> 2 from one end only
    rows, cols, cos, ratio, rank, count = _merged_both_ways(
        3, np.array([0, 2, 1]), np.array([2, 0, 2]), np.array([0.9, 0.9, 0.4], np.float32),
        np.array([0.5, 0.3, 0.8], np.float32), np.array([0, 1, 2]))
    assert list(zip(rows.tolist(), cols.tolist())) == [(0, 2), (1, 2), (2, 0), (2, 1)]  # (row, col) order
    np.testing.assert_array_equal(count, [2, 1, 2, 1])
    np.testing.assert_allclose(ratio, [0.3, 0.8, 0.3, 0.8])
    np.testing.assert_array_equal(rank, [0, 2, 0, 2])
    np.testing.assert_allclose(cos, [0.9, 0.4, 0.9, 0.4])
    assert cos.dtype == ratio.dtype == np.float32 and rank.dtype == count.dtype == np.int64


def test_merged_entries_match_a_dictionary_of_pairs():
    """On many random proposals (a third of them also made from the other end), the merge is what a
    dictionary keyed by (row, col) gives: every pair both ways, sorted, the lower ratio and rank,
    the count of its proposals, the cosine of its first."""
    from gcn_match_ros.graph import _merged_both_ways

    rng = np.random.default_rng(5)
    n = 60
    pairs = {(int(a), int(b)) for a, b in rng.integers(0, n, (900, 2)) if a != b}
    pairs = sorted(pairs | {(b, a) for a, b in list(pairs)[::3]})
    rows, cols = np.array(pairs).T
    pair_cos = {}
    cos = np.array([pair_cos.setdefault(frozenset(p), rng.random()) for p in pairs], np.float32)
    ratio, rank = rng.random(len(pairs)).astype(np.float32), rng.integers(0, 5, len(pairs))
    order = rng.permutation(len(pairs))  # proposals in no particular order
    got = _merged_both_ways(n, rows[order], cols[order], cos[order], ratio[order], rank[order])
    want = {}
    for a, b, c, q, k in zip(rows, cols, cos, ratio, rank):
        for key in ((a, b), (b, a)):
            old = want.get(key)
            want[key] = (c, q, k, 1) if old is None else (c, min(old[1], q), min(old[2], k), old[3] + 1)
    keys = sorted(want)
    assert list(zip(got[0].tolist(), got[1].tolist())) == keys
    np.testing.assert_array_equal(got[2], [want[k][0] for k in keys])
    np.testing.assert_array_equal(got[3], [want[k][1] for k in keys])
    np.testing.assert_array_equal(got[4], [want[k][2] for k in keys])
    np.testing.assert_array_equal(got[5], [want[k][3] for k in keys])
    assert got[5].max() == 2 and got[5].min() == 1


def test_edges_grow_linearly_not_quadratically():
    p = permuted_views_problem(n_views=4, n_points=400, noise=0.3, dim=32)
    g = build_graph(p, GraphConfig.paper(4))
    assert g.n_edges <= 2 * 4 * 3 * 400 * 4  # at most k per row per other view, both directions


def test_bad_config_is_refused():
    with pytest.raises(ValueError, match="k must"):
        GraphConfig(k=0)
    with pytest.raises(ValueError, match="ratio"):
        GraphConfig(ratio=1.5)


def test_taken_keeps_the_columns_themselves_when_everything_is_kept():
    a, b = np.arange(5), np.arange(5.0) * 2
    same = _taken(np.ones(5, bool), a, b)
    assert same[0] is a and same[1] is b
    sub = _taken(np.array([True, False, True, False, False]), a, b)
    assert sub[0].tolist() == [0, 2] and sub[1].tolist() == [0.0, 4.0]
