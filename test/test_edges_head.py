"""Tests of gcn_match_ros.edges.head: which models score edges, their candidate settings, the probabilities."""
import dataclasses

import numpy as np
import pytest
import torch

from gcn_match_ros.edges.candidates import EDGE_FEATURES, EdgeConfig, candidate_edges
from gcn_match_ros.edges.head import edge_config_of, edge_probabilities, has_edge_head
from gcn_match_ros.learn.model import GCN, GCNConfig, embed_problem
from gcn_match_ros.node_features import feature_dim

from conftest import SMALL_GCN_LAYERS, permuted_views_problem_with_attributes

PLAIN = GCNConfig(in_dim=feature_dim(16), **SMALL_GCN_LAYERS)
WITH_HEAD = dataclasses.replace(PLAIN, edge_features=len(EDGE_FEATURES), edge_hidden=8, edge_k=3)


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


def test_has_edge_head():
    torch.manual_seed(0)
    assert has_edge_head(GCN(WITH_HEAD))
    assert not has_edge_head(GCN(PLAIN))  # the paper's model: scores are EEᵀ
    assert not has_edge_head(torch.nn.Linear(2, 2))


def test_edge_config_of_takes_k_from_the_model():
    torch.manual_seed(0)
    assert edge_config_of(GCN(WITH_HEAD)) == EdgeConfig(k=3)
    assert edge_config_of(GCN(dataclasses.replace(WITH_HEAD, edge_k=6))).k == 6


def test_edge_probabilities_are_the_sigmoid_of_the_head_logits():
    problem = permuted_views_problem_with_attributes(n_views=3, p=12, dim=16)
    torch.manual_seed(0)
    model = GCN(WITH_HEAD)
    E, _ = embed_problem(model, problem)
    edges = candidate_edges(problem, edge_config_of(model))
    m = edges.rows.shape[0]
    assert m > 0 and edges.features.shape == (m, len(EDGE_FEATURES))
    emb = torch.from_numpy(E)
    with torch.no_grad():  # as at inference (the gcn solver runs it in inference mode)
        got = edge_probabilities(model, emb, edges)
        logits = model.score_edges(emb, torch.from_numpy(edges.rows), torch.from_numpy(edges.cols),
                                   torch.from_numpy(edges.features))
    assert got.shape == (m,) and got.dtype == np.float32
    np.testing.assert_allclose(got, torch.sigmoid(logits).numpy(), rtol=1e-6)
    assert np.all((got > 0) & (got < 1))
    # the head reads the edge features: other features, other probabilities
    shifted = dataclasses.replace(edges, features=edges.features + 1.0)
    with torch.no_grad():
        assert not np.allclose(edge_probabilities(model, emb, shifted), got)


def test_edge_probabilities_do_not_depend_on_the_callers_torch_threads():
    """The caller's count varies with timing (threads._take_core); on a Xeon the shipped head's
    GEMMs gave 2 of 5 833 probabilities of this window other last bits on two threads."""
    from gcn_match_ros import solvers
    from gcn_match_ros.data.synthetic import random_scene_problem, rome16k

    solver = solvers.create("gcn")
    problem = random_scene_problem(rome16k(3, n_points=300), rng=1)
    solver.prepare(problem)
    edges = candidate_edges(problem, solver.edge_config)
    with torch.inference_mode():
        E, _ = embed_problem(solver.model, problem, solver.graph_config, solver.meta["feature_config"])
    emb = torch.from_numpy(E)
    got = {}
    before = torch.get_num_threads()
    try:
        for threads in (2, 1):
            torch.set_num_threads(threads)
            got[threads] = edge_probabilities(solver.model, emb, edges)
            assert torch.get_num_threads() == threads  # the caller's count given back
    finally:
        torch.set_num_threads(before)
    np.testing.assert_array_equal(got[1], got[2])


def test_edge_probabilities_split_over_two_threads_equal_one_pass():
    """From SPLIT_EDGES edges on, the second half runs on the second thread (or back on the
    caller's when that thread is busy); halves meet at a chunk boundary, so the bits are those of
    one pass, whichever thread ran which half."""
    import threading

    from gcn_match_ros import solvers, threads
    from gcn_match_ros.data.synthetic import random_scene_problem, rome16k
    from gcn_match_ros.edges.head import SPLIT_EDGES

    solver = solvers.create("gcn")
    problem = random_scene_problem(rome16k(4, n_points=400), rng=2)
    solver.prepare(problem)
    edges = candidate_edges(problem, solver.edge_config)
    assert edges.rows.shape[0] > SPLIT_EDGES + 1000  # split, and not at the end
    with torch.inference_mode():
        E, _ = embed_problem(solver.model, problem, solver.graph_config, solver.meta["feature_config"])
    emb = torch.from_numpy(E)
    one_pass = edge_probabilities(solver.model, emb, edges, parallel=False)
    np.testing.assert_array_equal(edge_probabilities(solver.model, emb, edges), one_pass)
    # the second thread busy: the second half is taken back and run on the caller's thread
    release = threading.Event()
    with threads.alongside(release.wait, 10.0):
        busy = edge_probabilities(solver.model, emb, edges)
        release.set()
    np.testing.assert_array_equal(busy, one_pass)
