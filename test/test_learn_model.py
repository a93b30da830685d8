"""Tests of gcn_match_ros.learn.model: normalisation, batching, shapes, gradcheck, overfitting one problem."""
import json

import numpy as np
import pytest
import torch

from gcn_match_ros.learn.losses import reconstruction_loss
from gcn_match_ros.learn.model import GCN, GCNConfig, collate, embed_problem, gcn_norm, normalized_adjacency
from gcn_match_ros.node_features import feature_dim

from conftest import (SMALL_GCN_LAYERS as SMALL, gcn_inputs as inputs,
                      permuted_views_problem_with_attributes as permuted_problem)


@pytest.fixture(autouse=True, scope="module")
def _one_thread(one_torch_thread):
    """Tiny graphs: one intra-op thread is fastest and immune to a busy shared CPU."""


# ---------------------------------------------------------------------------
# gcn_norm
# ---------------------------------------------------------------------------
def _dense(index, weight, n):
    A = torch.zeros(n, n, dtype=weight.dtype)
    A.index_put_((index[0], index[1]), weight, accumulate=True)
    return A


def test_gcn_norm_equals_dense_formula():
    ei = torch.tensor([[0, 1, 0, 2, 1, 3], [1, 0, 2, 0, 3, 1]])
    ew = torch.tensor([0.5, 0.5, 1.0, 1.0, 0.25, 0.25], dtype=torch.float64)
    n = 5  # node 4 isolated
    A = _dense(ei, ew, n)
    D = torch.diag(1.0 + A.sum(1))
    Dm = torch.diag(torch.diag(D).rsqrt())
    ref = Dm @ (A + torch.eye(n, dtype=torch.float64)) @ Dm
    idx, w = gcn_norm(ei, ew, n)
    assert idx.shape == (2, 6 + n) and w.shape == (6 + n,)
    assert torch.allclose(_dense(idx, w, n), ref)
    assert torch.allclose(normalized_adjacency(ei, ew, n).to_dense(), ref)
    # hand value: node 0 has degree 1 + 1.5, node 1 1 + 0.75
    assert w[0].item() == pytest.approx(0.5 / np.sqrt(2.5 * 1.75))
    assert _dense(idx, w, n)[4, 4].item() == pytest.approx(1.0)


def test_gcn_norm_folds_existing_self_loops():
    ei = torch.tensor([[0, 1, 1], [1, 0, 1]])
    ew = torch.tensor([1.0, 1.0, 0.5], dtype=torch.float64)
    A = _dense(ei, ew, 2)
    d = 1.0 + A.sum(1)
    ref = (A + torch.eye(2, dtype=torch.float64)) / torch.sqrt(d[:, None] * d[None, :])
    idx, w = gcn_norm(ei, ew, 2)
    assert idx.shape == (2, 4)  # one diagonal entry per node
    assert torch.allclose(_dense(idx, w, 2), ref)


# ---------------------------------------------------------------------------
# forward
# ---------------------------------------------------------------------------
def test_output_rows_unit_norm_and_shape():
    prob = permuted_problem()
    x, ei, ew, _ = inputs(prob)
    torch.manual_seed(0)
    model = GCN(GCNConfig(in_dim=x.shape[1], **SMALL)).eval()
    E = model(x, ei, ew)
    assert E.shape == (60, 12)
    assert torch.allclose(E.norm(dim=1), torch.ones(60), atol=1e-5)


def test_default_config_forward_and_embed_problem():
    prob = permuted_problem(n_views=4, p=30, dim=128)
    cfg = GCNConfig(in_dim=feature_dim(128))
    assert cfg.in_dim == 132 and len(cfg.widths) == 12
    model = GCN(cfg)
    E, g = embed_problem(model, prob)
    assert E.shape == (120, cfg.out_dim) and E.dtype == np.float32
    assert np.allclose(np.linalg.norm(E, axis=1), 1.0, atol=1e-5)
    assert model.training  # restored


@pytest.mark.parametrize("norm", ["graph", "node", "none"])
def test_batched_forward_equals_separate(norm):
    p1, p2 = permuted_problem(3, 20, seed=1), permuted_problem(4, 13, seed=2)
    x1, ei1, ew1, g1 = inputs(p1)
    x2, ei2, ew2, g2 = inputs(p2)
    torch.manual_seed(0)
    model = GCN(GCNConfig(in_dim=x1.shape[1], norm=norm, **SMALL)).eval()
    x, ei, ew, ptr = collate([(x1.numpy(), g1), (x2, ei2, ew2)])
    assert ptr.tolist() == [0, 60, 112] and x.shape == (112, x1.shape[1])
    assert ei.shape[1] == ei1.shape[1] + ei2.shape[1]
    with torch.no_grad():
        both = model(x, ei, ew, ptr)
        a, b = model(x1, ei1, ew1), model(x2, ei2, ew2)
    assert torch.allclose(both[:60], a, atol=1e-5)
    assert torch.allclose(both[60:], b, atol=1e-5)


def test_model_gradcheck_float64():
    prob = permuted_problem(2, 5, dim=4)
    x, ei, ew, _ = inputs(prob)
    torch.manual_seed(0)
    model = GCN(GCNConfig(in_dim=x.shape[1], widths=(4, 4, 4), out_dim=3, groups=2, skip_layers=(2, 3))).double()
    x = x.double().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: model(z, ei, ew.double()), (x,), eps=1e-6, atol=1e-6)


def test_bad_shapes_raise_naming_the_shape():
    prob = permuted_problem()
    x, ei, ew, _ = inputs(prob)
    model = GCN(GCNConfig(in_dim=x.shape[1], **SMALL))
    F = x.shape[1]
    with pytest.raises(ValueError, match=rf"x: expected shape \(N, {F}\), got \(60, 7\)"):
        model(x[:, :7], ei, ew)
    with pytest.raises(ValueError, match=r"x: expected shape .*got \(60, 1, 20\)"):
        model(x[:, None], ei, ew)
    with pytest.raises(ValueError, match=r"edge_index: expected shape \(2, E\), got \(3, "):
        model(x, torch.cat([ei, ei[:1]]), ew)
    with pytest.raises(ValueError, match=r"edge_weight: expected shape \(\d+,\)"):
        model(x, ei, ew[:-1])
    with pytest.raises(ValueError, match=r"edge_index: node indices must lie in \[0, 50\)"):
        model(x[:50], ei, ew)
    with pytest.raises(ValueError, match=r"edge_index: expected an integer dtype"):
        model(x, ei.float(), ew)
    with pytest.raises(ValueError, match=r"node_ptr: must start at 0"):
        model(x, ei, ew, torch.tensor([0, 30, 59]))
    with pytest.raises(ValueError, match=r"items\[1\].x: expected shape \(N, 20\), got \(5, 3\)"):
        collate([(x, ei, ew), (torch.zeros(5, 3), torch.zeros(2, 0, dtype=torch.int64), torch.zeros(0))])
    with pytest.raises(ValueError, match="not divisible by groups"):
        GCNConfig(widths=(10, 12), groups=4, skip_layers=())
    with pytest.raises(ValueError, match="skip_layers"):
        GCNConfig(widths=(8, 8), groups=4, skip_layers=(3,))


def test_config_dict_round_trip():
    cfg = GCNConfig(in_dim=20, **SMALL)
    d = json.loads(json.dumps(cfg.to_dict()))
    assert GCNConfig.from_dict(d) == cfg
    with pytest.raises(ValueError, match="unknown keys"):
        GCNConfig.from_dict({**d, "depth": 3})


# ---------------------------------------------------------------------------
# overfitting one problem
# ---------------------------------------------------------------------------
def test_small_gcn_overfits_one_problem():
    torch.manual_seed(0)
    prob = permuted_problem(3, 20, dim=16, noise=0.3, seed=3)
    x, ei, ew, g = inputs(prob)
    model = GCN(GCNConfig(in_dim=x.shape[1], widths=(32, 32, 32, 32), out_dim=32, groups=4, skip_layers=(2, 4)))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    vo = prob.view_offsets
    first = None
    for _ in range(250):
        opt.zero_grad()
        loss = reconstruction_loss(model(x, ei, ew), ei, ew, 60, vo, "l1")
        loss.backward()
        opt.step()
        first = loss.item() if first is None else first
    final = loss.item()
    assert final < 0.4 * first, (first, final)
    with torch.no_grad():
        S = (lambda E: E @ E.T)(model.eval()(x, ei, ew)).numpy()
    gt = prob.gt_track
    view = prob.view_index
    cross = view[:, None] != view[None, :]
    true = (gt[:, None] == gt[None, :]) & cross
    pred = (S > 0.5) & cross
    recall = (pred & true).sum() / true.sum()
    # it reproduces the graph: pairs that are not candidate edges stay below 0.5
    non_edges = cross & (g.adjacency().toarray() == 0)
    false_rate = (pred & non_edges).sum() / non_edges.sum()
    assert recall > 0.8 and false_rate < 0.05, (recall, false_rate)


def test_edge_scores_at_inference_equal_the_training_path_across_chunks():
    """More candidate edges than one inference chunk: the chunked, in-place path gives the same
    logits as the differentiable one."""
    from gcn_match_ros.learn.model import EDGE_CHUNK

    torch.manual_seed(0)
    model = GCN(GCNConfig(in_dim=12, widths=(8, 8), out_dim=8, groups=2, skip_layers=(), edge_features=5,
                          edge_hidden=16)).eval()
    E = torch.nn.functional.normalize(torch.randn(300, 8), dim=1)
    m = 2 * EDGE_CHUNK + 7
    rows, cols = torch.randint(0, 300, (m,)), torch.randint(0, 300, (m,))
    x = torch.rand(m, 5)
    trained = model.score_edges(E, rows, cols, x)
    assert trained.requires_grad
    with torch.no_grad():
        inferred = model.score_edges(E, rows, cols, x)
    assert inferred.shape == (m,)
    torch.testing.assert_close(inferred, trained.detach(), rtol=0, atol=1e-6)
    with torch.no_grad():
        assert model.score_edges(E, rows[:0], cols[:0], x[:0]).shape == (0,)


def test_compiled_adjacency_is_bit_for_bit_the_torch_ops():
    """At inference (CPU, float32, no gradient) Â comes from one compiled pass; with a gradient
    it comes from gcn_norm and a sort: the same tensor, on sorted and unsorted graphs with
    duplicate edges, self loops and isolated nodes."""
    rng = np.random.default_rng(0)
    for trial in range(40):
        n = int(rng.integers(1, 60))
        e = int(rng.integers(0, 400))
        ei = torch.from_numpy(rng.integers(0, n, (2, e)))
        if trial % 2:  # sorted by (row, col), as build_graph and collate give them
            ei = ei[:, torch.from_numpy(np.lexsort((ei[1].numpy(), ei[0].numpy())))]
        ew = torch.from_numpy(rng.random(e).astype(np.float32))
        fast = normalized_adjacency(ei, ew, n)
        with torch.enable_grad():
            slow = normalized_adjacency(ei, ew.clone().requires_grad_(), n)
        assert torch.equal(fast.crow_indices(), slow.crow_indices())
        assert torch.equal(fast.col_indices(), slow.col_indices())
        assert torch.equal(fast.values(), slow.values().detach())
    with pytest.raises(ValueError, match="node indices"):
        normalized_adjacency(torch.tensor([[0], [5]]), torch.ones(1), 3)
