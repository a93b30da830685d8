"""Tests of gcn_match_ros.similarity: descriptor similarity blocks, computed once per view pair and shared."""
import dataclasses
import threading

import numpy as np
import pytest
import torch

from gcn_match_ros.data import synthetic
from gcn_match_ros.descriptors import NORMALIZATIONS, normalize_descriptors
from gcn_match_ros.edges.candidates import EdgeConfig, candidate_edges
from gcn_match_ros.graph import GraphConfig, build_graph
from gcn_match_ros.similarity import DescriptorSimilarity, most_similar

from conftest import permuted_views_problem


def _block_bytes(problem, i, j):
    return int(problem.view_sizes[i] * problem.view_sizes[j] * 4)  # float32


@pytest.mark.parametrize("normalization", NORMALIZATIONS)
def test_block_is_the_product_of_normalised_descriptors(normalization):
    problem = permuted_views_problem(n_views=3, n_points=10, noise=0.2)
    sim = DescriptorSimilarity(problem)
    d = torch.from_numpy(normalize_descriptors(problem.descriptors, normalization))
    offs = problem.view_offsets
    for i in range(3):
        for j in range(i + 1, 3):
            expected = d[offs[i]:offs[i + 1]] @ d[offs[j]:offs[j + 1]].T
            blk = sim.block(i, j, normalization)
            assert blk.dtype == torch.float32 and torch.equal(blk, expected)
            # the other direction is the transpose, the same memory, not computed again
            computed = sim.computed
            back = sim.block(j, i, normalization)
            assert torch.equal(back, blk.T) and back.data_ptr() == blk.data_ptr()
            assert sim.computed == computed
    assert torch.equal(sim.view(1, normalization), d[offs[1]:offs[2]])


def test_each_block_is_computed_once_per_normalization():
    problem = permuted_views_problem(n_views=3, n_points=8)
    sim = DescriptorSimilarity(problem)
    first = sim.block(0, 1, "l2")
    assert sim.block(0, 1, "l2") is first and sim.computed == 1
    sim.block(1, 0, "l2")
    sim.block(0, 2, "l2")
    assert sim.computed == 2
    sim.block(0, 1, "rootsift")  # another similarity: a block of its own
    assert sim.computed == 3 and sim.recomputed == 0
    assert sim.cached_bytes == 3 * _block_bytes(problem, 0, 1)


def test_a_small_budget_evicts_least_recently_used_blocks():
    problem = permuted_views_problem(n_views=3, n_points=8)
    one_block = _block_bytes(problem, 0, 1)
    sim = DescriptorSimilarity(problem, budget_bytes=one_block)
    a = sim.block(0, 1, "l2")
    sim.block(0, 2, "l2")  # evicts (0, 1)
    assert sim.cached_bytes == one_block and sim.recomputed == 0
    again = sim.block(0, 1, "l2")
    assert (sim.computed, sim.recomputed) == (3, 1)
    assert torch.equal(again, a)  # the same values, computed again
    # a block larger than the whole budget is never kept
    none_kept = DescriptorSimilarity(problem, budget_bytes=0)
    for _ in range(3):
        none_kept.block(1, 2, "l2")
    assert (none_kept.computed, none_kept.recomputed, none_kept.cached_bytes) == (3, 2, 0)


def test_unknown_normalization_is_refused():
    sim = DescriptorSimilarity(permuted_views_problem())
    with pytest.raises(ValueError, match=r"normalization must be one of \('l2', 'rootsift'\), got 'l1'"):
        sim.block(0, 1, "l1")


def _same_arrays(a, b) -> bool:
    """Every field equal; dicts (an EdgeSet's models) key by key, field by field."""
    def same(x, y):
        if isinstance(x, dict):
            return x.keys() == y.keys() and all(same(x[k], y[k]) for k in x)
        if dataclasses.is_dataclass(x):
            return y is not None and _same_arrays(x, y)
        if x is None or y is None:
            return x is y
        return np.array_equal(x, y)
    return all(same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))


def test_graph_and_candidates_are_the_same_with_a_shared_similarity():
    problem = synthetic.random_scene_problem(synthetic.rome16k(3), np.random.default_rng([7, 0]))
    graph_config, edge_config = GraphConfig(), EdgeConfig()
    assert graph_config.normalization != edge_config.normalization  # two similarities per view pair
    shared = DescriptorSimilarity(problem)
    graph = build_graph(problem, graph_config, shared)
    edges = candidate_edges(problem, edge_config, shared)
    assert _same_arrays(graph, build_graph(problem, graph_config))
    assert _same_arrays(edges, candidate_edges(problem, edge_config))
    assert edges.rows.size > 0 and graph.n_edges > 0
    # every (normalization, view pair) block computed once, and read again from the cache
    assert (shared.computed, shared.recomputed) == (2 * 3, 0)
    build_graph(problem, graph_config, shared)
    candidate_edges(problem, edge_config, shared)
    assert shared.computed == 2 * 3


def test_most_similar_equals_a_stable_sort_of_rows_and_columns():
    rng = np.random.default_rng(0)
    x = rng.random((37, 29)).astype(np.float32)
    x[3, [4, 9, 17]] = x[3, 2]  # ties: the lower index first
    x[[5, 30], 8] = x[1, 8]
    coarse = np.round(rng.random((60, 203)) * 8).astype(np.float32)  # ties everywhere, many chunks
    for block, k_row, k_col in ((x, 1, 1), (x, 2, 2), (x, 7, 8), (x, 11, 11), (x, 29, 37), (x.T, 11, 4),
                                (coarse, 11, 11), (coarse.T, 4, 17), (coarse, 203, 60)):
        rv, ri, cv, ci = most_similar(block, k_row, k_col)
        for rows, values, indices, k in ((block, rv, ri, k_row), (block.T, cv, ci, k_col)):
            order = np.argsort(-rows, axis=1, kind="stable")[:, :k]
            np.testing.assert_array_equal(indices, order)
            np.testing.assert_array_equal(values, np.take_along_axis(rows, order, 1))
    with pytest.raises(ValueError, match="k_row"):
        most_similar(x, 30, 1)


def test_two_threads_reading_blocks_at_once_get_each_block_computed_once():
    problem = permuted_views_problem(n_views=4, n_points=30, noise=0.2)
    sim = DescriptorSimilarity(problem)
    barrier = threading.Barrier(2)
    got = {}

    def read(name):
        barrier.wait()
        got[name] = [sim.block(i, j, norm) for norm in NORMALIZATIONS for i in range(4) for j in range(i + 1, 4)]

    threads = [threading.Thread(target=read, args=(n,)) for n in ("a", "b")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    # the two readers hold the same tensors: a block computed twice (both asked at once) is kept once
    assert all(x is y for x, y in zip(got["a"], got["b"]))
    assert sim.computed == len(NORMALIZATIONS) * 6 and sim.recomputed == 0
    assert sim.cached_bytes == sum(x.numel() * 4 for x in got["a"])


def _lists_equal(got, want):
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_a_view_pairs_best_lists_are_computed_once_and_shared_as_prefixes(monkeypatch):
    import gcn_match_ros.similarity as module

    problem = permuted_views_problem(n_views=3, n_points=30, noise=0.3)
    calls = []
    real = module.most_similar
    monkeypatch.setattr(module, "most_similar", lambda s, kr, kc: calls.append((kr, kc)) or real(s, kr, kc))
    sim = DescriptorSimilarity(problem, top_k={"rootsift": 11})
    block = sim.block(0, 1, "rootsift").numpy()
    # the first reader asks for 4: computed at the declared 11, and its 4 are the first 4 of 11
    _lists_equal(sim.most_similar(0, 1, "rootsift", 4, 4), real(block, 4, 4))
    _lists_equal(sim.most_similar(0, 1, "rootsift", 11, 11), real(block, 11, 11))
    assert calls == [(11, 11)]
    # the other direction swaps rows and columns, from the same lists
    rv, ri, cv, ci = real(block, 11, 11)
    _lists_equal(sim.most_similar(1, 0, "rootsift", 5, 3), (cv[:, :5], ci[:, :5], rv[:, :3], ri[:, :3]))
    assert calls == [(11, 11)]
    # undeclared: computed at what is asked for, again when more is asked for
    _lists_equal(sim.most_similar(0, 2, "l2", 2, 2), real(sim.block(0, 2, "l2").numpy(), 2, 2))
    _lists_equal(sim.most_similar(0, 2, "l2", 6, 6), real(sim.block(0, 2, "l2").numpy(), 6, 6))
    assert calls[1:] == [(2, 2), (6, 6)]


def test_two_threads_asking_for_one_pairs_best_lists_compute_them_once(monkeypatch):
    import gcn_match_ros.similarity as module

    problem = permuted_views_problem(n_views=2, n_points=40, noise=0.3)
    started, release, calls = threading.Event(), threading.Event(), []
    real = module.most_similar

    def slow(s, kr, kc):
        calls.append(threading.current_thread().name)
        started.set()
        assert release.wait(5)
        return real(s, kr, kc)

    monkeypatch.setattr(module, "most_similar", slow)
    sim = DescriptorSimilarity(problem)
    got = {}
    first = threading.Thread(target=lambda: got.setdefault("first", sim.most_similar(0, 1, "l2", 3, 3)))
    first.start()
    assert started.wait(5)
    second = threading.Thread(target=lambda: got.setdefault("second", sim.most_similar(0, 1, "l2", 3, 3)))
    second.start()
    release.set()
    first.join(5)
    second.join(5)
    assert len(calls) == 1
    _lists_equal(got["first"], got["second"])
