"""Tests of gcn_match_ros.solvers (every registered method): known answers, settings, input checks, node limits."""
# pygmtools-style: problems with a known answer (V views, each a random permutation of p scene
# points, the input graph = exactly the true pairs) must be recovered exactly by every registered
# solver, with cycle-consistent tracks; then partial visibility, a few wrong edges, settings
# parsing, input validation and the dense methods' node limit.
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from gcn_match_ros.graph import CorrespondenceGraph
from gcn_match_ros.metrics import score_result
from gcn_match_ros.problem import Problem
from gcn_match_ros.rounding import is_cycle_consistent
from gcn_match_ros import solvers
from gcn_match_ros.solvers import available_solvers
from gcn_match_ros.solvers.clear import clear
from gcn_match_ros.solvers.matchals import matchals
from gcn_match_ros.solvers.matcheig import matcheig
from gcn_match_ros.solvers.pgdds import pgdds
from gcn_match_ros.solvers.quickmatch import quickmatch
from gcn_match_ros.solvers.spectral import spectral

from conftest import (corrupted_pairs, graph_from_pairs, known_answer_problem as make_problem,
                      true_pair_list as true_pairs)

SOLVERS = [s for s in available_solvers() if s != "gcn"]
#: Settings for the exact-recovery tests. PGDDS descends from a random start and can stop at a
#: stationary point where one track's rows are spread evenly over several universe points (recall
#: 0.95 on one of these problems); the original's perturb-and-restart step gets it out. (Not the
#: default: on the Oxford problems the restarts cost precision.)
EXACT = {"pgdds": "pgdds:restarts=2,perturbation=0.2"}
#: Permutation-synchronisation methods: they should repair a few wrong input edges.
ROBUST = ["spectral", "matcheig", "clear", "matchals"]


# -- solve and score (problems with a known answer: conftest.known_answer_problem) -------------
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
