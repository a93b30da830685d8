"""Tests of the multi-view matching solvers (gcn_match_ros/solvers/).

pygmtools-style: problems with a known answer (V views, each a random permutation of p scene
points, the input graph = exactly the true pairs) must be recovered exactly by every registered
solver, with cycle-consistent tracks; then partial visibility, a few wrong edges, settings
parsing, input validation and the dense methods' node limit.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.sparse as sp

from gcn_match_ros.graph import CorrespondenceGraph
from gcn_match_ros.metrics import score_result
from gcn_match_ros.problem import Problem
from gcn_match_ros.rounding import estimate_universe_size, is_cycle_consistent
from gcn_match_ros import solvers
from gcn_match_ros.solvers import available_solvers
from gcn_match_ros.solvers.clear import clear
from gcn_match_ros.solvers.matchals import matchals
from gcn_match_ros.solvers.matcheig import matcheig
from gcn_match_ros.solvers.pgdds import pgdds
from gcn_match_ros.solvers.quickmatch import quickmatch
from gcn_match_ros.solvers.spectral import spectral

SOLVERS = [s for s in available_solvers() if s != "gcn"]
#: Settings for the exact-recovery tests. PGDDS descends from a random start and can stop at a
#: stationary point where one track's rows are spread evenly over several universe points (recall
#: 0.95 on one of these problems); the original's perturb-and-restart step gets it out. (Not the
#: default: on the Oxford problems the restarts cost precision.)
EXACT = {"pgdds": "pgdds:restarts=2,perturbation=0.2"}
#: Permutation-synchronisation methods: they should repair a few wrong input edges.
ROBUST = ["spectral", "matcheig", "clear", "matchals"]


# -- problems with a known answer --------------------------------------------------------------
def make_problem(n_views: int, n_points: int, visibility: float = 1.0, seed: int = 0, dim: int = 16) -> Problem:
    """Each view sees a random subset (all when visibility = 1) of p points in random order.

    Descriptors are the point's descriptor, identical in every view (noiseless); gt_track is the
    point id, -1 for a point seen by a single view.
    """
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(n_points, dim))
    seen = rng.random((n_views, n_points)) < visibility
    seen[rng.integers(n_views, size=n_points), np.arange(n_points)] = True  # every point somewhere
    ids = [rng.permutation(np.flatnonzero(seen[v])) for v in range(n_views)]
    gt = np.concatenate(ids)
    n_seen = seen.sum(axis=0)
    gt = np.where(n_seen[gt] >= 2, gt, -1)
    offsets = np.r_[0, np.cumsum([len(i) for i in ids])]
    return Problem(view_offsets=offsets, keypoints=rng.uniform(0, 100, size=(len(gt), 2)),
                   descriptors=base[np.concatenate(ids)], gt_track=gt, name=f"perm{n_views}x{n_points}")


def true_pairs(problem: Problem):
    gt, view = problem.gt_track, problem.view_index
    out = []
    for g in np.unique(gt[gt >= 0]):
        idx = np.flatnonzero(gt == g)
        out += [(int(a), int(b)) for a, b in itertools.combinations(idx, 2) if view[a] != view[b]]
    return out


def graph_from_pairs(problem: Problem, pairs) -> CorrespondenceGraph:
    """Binary graph with exactly these undirected pairs (stored both ways, sorted)."""
    pairs = np.asarray(sorted(set((min(a, b), max(a, b)) for a, b in pairs)), np.int64).reshape(-1, 2)
    rows = np.r_[pairs[:, 0], pairs[:, 1]]
    cols = np.r_[pairs[:, 1], pairs[:, 0]]
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    e = rows.size
    return CorrespondenceGraph(problem.view_offsets.copy(), rows, cols, np.ones(e, np.float32),
                               np.ones(e, np.float32), np.zeros(e, np.float32), np.zeros(e, np.int64))


def corrupted_pairs(problem: Problem, fraction: float, seed: int = 0):
    """True pairs with ``fraction`` of them removed and as many wrong cross-view pairs added."""
    rng = np.random.default_rng(seed)
    pairs = true_pairs(problem)
    k = max(1, int(round(fraction * len(pairs))))
    keep = [pairs[i] for i in sorted(rng.choice(len(pairs), len(pairs) - k, replace=False))]
    gt, view, n = problem.gt_track, problem.view_index, problem.n_keypoints
    wrong = set()
    while len(wrong) < k:
        a, b = (int(x) for x in rng.integers(n, size=2))
        if view[a] != view[b] and (gt[a] != gt[b] or gt[a] < 0):
            wrong.add((min(a, b), max(a, b)))
    return keep + sorted(wrong)


def solve_and_score(spec: str, problem: Problem, graph: CorrespondenceGraph):
    result = solvers.create(spec).solve(problem, graph)
    assert is_cycle_consistent(result.track, problem.view_index), f"{spec}: tracks not cycle-consistent"
    result.validate_against(problem)
    assert np.all((result.pair_scores >= 0) & (result.pair_scores <= 1))
    return score_result(problem, result)


# -- exact recovery ----------------------------------------------------------------------------
@pytest.mark.parametrize("n_views,n_points,seed", [(3, 10, 0), (4, 20, 1), (5, 30, 2)])
@pytest.mark.parametrize("name", SOLVERS)
def test_exact_recovery_full_visibility(name, n_views, n_points, seed):
    prob = make_problem(n_views, n_points, seed=seed)
    sc = solve_and_score(EXACT.get(name, name), prob, graph_from_pairs(prob, true_pairs(prob)))
    assert sc["P"] == 1.0 and sc["R"] == 1.0, (name, sc)


@pytest.mark.parametrize("name", SOLVERS)
def test_exact_recovery_partial_visibility(name):
    prob = make_problem(4, 25, visibility=0.6, seed=3)
    assert np.any(prob.gt_track == -1) and len(set(prob.view_sizes)) > 1
    sc = solve_and_score(EXACT.get(name, name), prob, graph_from_pairs(prob, true_pairs(prob)))
    assert sc["P"] == 1.0 and sc["R"] == 1.0, (name, sc)


@pytest.mark.parametrize("name", SOLVERS)
def test_a_graph_without_edges_matches_nothing(name):
    """Views with 0-2 keypoints and no candidate edge (a low-texture window): every keypoint
    unmatched, no error (matcheig used to index its scores with empty arrays and fail)."""
    prob = Problem(view_offsets=np.array([0, 1, 1, 3]), keypoints=np.zeros((3, 2)),
                   descriptors=np.eye(3, 16), gt_track=np.array([-1, -1, -1]), name="sparse")
    result = solvers.create(name).solve(prob, graph_from_pairs(prob, []))
    np.testing.assert_array_equal(result.track, [-1, -1, -1])


@pytest.mark.parametrize("name", ROBUST)
def test_robust_to_a_few_wrong_edges(name):
    """5% of the true edges dropped and as many wrong ones added: synchronisation repairs them."""
    prob = make_problem(5, 20, seed=4)
    graph = graph_from_pairs(prob, corrupted_pairs(prob, 0.05, seed=4))
    floor = solve_and_score("nn:threshold=0", prob, graph)
    sc = solve_and_score(name, prob, graph)
    assert floor["P"] < 1.0 and floor["R"] < 1.0  # the input really is corrupted
    assert sc["F1"] > floor["F1"], (name, sc["F1"], floor["F1"])
    assert sc["P"] == 1.0 and sc["R"] >= 0.95, (name, sc)


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


# -- settings ----------------------------------------------------------------------------------
def test_get_solver_parses_settings():
    s = solvers.create("matchals:iters=7,alpha=20,rounding=greedy,graph=ratio0.8")
    assert (s.config.iters, s.config.alpha, s.config.rounding, s.config.graph) == (7, 20.0, "greedy", "ratio0.8")
    assert isinstance(s.config.iters, int) and s.describe().startswith("matchals:")
    assert solvers.create("spectral:universe=40").config.universe == "40"
    assert solvers.create("clear:isolate=true,soft=embedding").config.isolate is True
    assert solvers.create("matcheig:threshold=0.3,rounding=repair").config.threshold == 0.3
    assert solvers.create("pgdds:gamma=0.25,iters=5").config.gamma == 0.25
    assert solvers.create("quickmatch:rho_edge=0.8,candidates=all").config.rho_edge == 0.8
    for name in SOLVERS:
        assert solvers.create(name).name == name  # defaults construct
    for bad in ("matchals:iters=many", "matchals:nosuch=1", "spectral:universe=-3", "clear:soft=maybe",
                "matcheig:rounding=best", "pgdds:gamma=2", "spectral:graph=nosuch"):
        with pytest.raises(ValueError):
            solvers.create(bad)


def test_universe_setting_is_used():
    prob = make_problem(3, 10, seed=0)
    graph = graph_from_pairs(prob, true_pairs(prob))
    for name in ("spectral", "matcheig"):
        assert solve_and_score(f"{name}:universe=10", prob, graph)["F1"] == 1.0
        # a universe of 3 points holds 3 of the 10 tracks: precision stays, recall drops to 0.3
        sc = solve_and_score(f"{name}:universe=3", prob, graph)
        assert sc["P"] == 1.0 and sc["R"] == pytest.approx(0.3), (name, sc)


# -- input validation --------------------------------------------------------------------------
FUNCTIONS = {
    "spectral": lambda a, o: spectral(a, o),
    "matcheig": lambda a, o: matcheig(a, o),
    "clear": lambda a, o: clear(a, o),
    "matchals": lambda a, o: matchals(a, o, iters=2),
    "pgdds": lambda a, o: pgdds(a, o, iters=2),
}


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_bad_input_names_the_argument(name):
    fn = FUNCTIONS[name]
    a = sp.random(12, 12, density=0.2, random_state=0)
    with pytest.raises(ValueError, match="adjacency"):
        fn(np.zeros((12, 11)), np.array([0, 6, 12]))
    with pytest.raises(ValueError, match="adjacency"):
        fn(np.zeros((2, 12, 12)), np.array([0, 6, 12]))
    with pytest.raises(ValueError, match="view_offsets"):
        fn(a, np.array([0, 6, 11]))  # does not end at N
    with pytest.raises(ValueError, match="view_offsets"):
        fn(a, np.array([0, 8, 6, 12]))  # decreasing
    with pytest.raises(ValueError, match="view_offsets"):
        fn(a, np.array([[0, 6, 12]]))


def test_quickmatch_bad_input_names_the_argument():
    d = np.random.default_rng(0).normal(size=(12, 8))
    with pytest.raises(ValueError, match="view_offsets"):
        quickmatch(d, np.array([0, 6, 11]))
    with pytest.raises(ValueError, match="descriptors"):
        quickmatch(d[0], np.array([0, 6, 12]))
    with pytest.raises(ValueError, match="adjacency"):
        quickmatch(d, np.array([0, 6, 12]), adjacency=np.zeros((12, 10)))


def test_public_functions_accept_dense_and_sparse():
    prob = make_problem(3, 10, seed=5)
    adj = graph_from_pairs(prob, true_pairs(prob)).adjacency()
    for fn in (spectral, matcheig, clear):
        t_sparse = fn(adj, prob.view_offsets)
        t_dense = fn(adj.toarray(), prob.view_offsets)
        np.testing.assert_array_equal(t_sparse, t_dense)
        assert is_cycle_consistent(t_sparse, prob.view_index)


# -- node limits of the dense methods ----------------------------------------------------------
def test_dense_methods_refuse_above_node_limit():
    prob = make_problem(3, 30, seed=6)  # N = 90
    adj = graph_from_pairs(prob, true_pairs(prob)).adjacency()
    with pytest.raises(ValueError, match="max_nodes=50"):
        matchals(adj, prob.view_offsets, max_nodes=50)
    with pytest.raises(ValueError, match="max_nodes=50"):
        pgdds(adj, prob.view_offsets, max_nodes=50)
    with pytest.raises(ValueError, match="max_nodes=50"):
        quickmatch(prob.descriptors, prob.view_offsets, adjacency=None, max_nodes=50)
    with pytest.raises(ValueError, match="max_nodes"):
        solvers.create("matchals:max_nodes=50").solve(prob, graph_from_pairs(prob, true_pairs(prob)))
    # the spectral methods decompose per connected component: only a large component is refused
    assert is_cycle_consistent(spectral(adj, prob.view_offsets, max_nodes=5), prob.view_index)
    connected = np.ones((90, 90))  # every cross-view pair: one component of 90 keypoints
    for fn in (spectral, matcheig, clear):
        with pytest.raises(ValueError, match="max_nodes=50"):
            fn(connected, prob.view_offsets, max_nodes=50)
