"""Tests of gcn_match_ros.learn.losses: hand-computed values, dense references, gradcheck."""
import numpy as np
import pytest
import torch

from gcn_match_ros.geometry import epipolar_residuals
from gcn_match_ros.learn.losses import epipolar_loss, reconstruction_loss
from gcn_match_ros.node_features import calibrated_points

from conftest import calibrated_scene as _scene

D64 = torch.float64


def _edges(pairs, weights):
    """Undirected (i, j, w) -> both directions."""
    r = [i for i, j in pairs] + [j for i, j in pairs]
    c = [j for i, j in pairs] + [i for i, j in pairs]
    return torch.tensor([r, c], dtype=torch.int64), torch.tensor(list(weights) * 2, dtype=D64)


# ---------------------------------------------------------------------------
# Reconstruction loss
# ---------------------------------------------------------------------------
def test_reconstruction_hand_computed_three_views():
    # one node per view, edge 0-1 (0.5); E rows e0=(1,0), e1=(0,1), e2=(1,0)
    E = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]], dtype=D64)
    ei, ew = _edges([(0, 1)], [0.5])
    # T = A+I = [[1,.5,0],[.5,1,0],[0,0,1]], S = [[1,0,1],[0,1,0],[1,0,1]]
    assert reconstruction_loss(E, ei, ew, 3, [0, 1, 2, 3], "l1").item() == pytest.approx(3.0 / 9)
    assert reconstruction_loss(E, ei, ew, 3, [0, 1, 2, 3], "l2").item() == pytest.approx(2.5 / 9)
    # without identity the diagonal (S_ii = 1) costs 1 each
    assert reconstruction_loss(E, ei, ew, 3, [0, 1, 2, 3], "l1", include_identity=False).item() \
        == pytest.approx(6.0 / 9)


def test_reconstruction_hand_computed_within_view_mask():
    # views {0, 1} and {2}; edges 0-2 (1.0), 1-2 (0.5)
    E = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.6, 0.8]], dtype=D64)
    ei, ew = _edges([(0, 2), (1, 2)], [1.0, 0.5])
    # |T - S| = [[0,1,.4],[1,0,.1],[.4,.1,0]]
    vo = [0, 2, 3]
    assert reconstruction_loss(E, ei, ew, 3, vo, "l1").item() == pytest.approx(3.0 / 9)
    assert reconstruction_loss(E, ei, ew, 3, vo, "l2").item() == pytest.approx(2.34 / 9)
    # masked: the within-view pair (0,1) is dropped; counted = 9 - (4 + 1) + 3 diagonal = 7
    assert reconstruction_loss(E, ei, ew, 3, vo, "l1", include_within_view=False).item() \
        == pytest.approx(1.0 / 7)
    assert reconstruction_loss(E, ei, ew, 3, vo, "l2", include_within_view=False).item() \
        == pytest.approx(0.34 / 7)
    # masked, no identity: only the 4 cross-view entries
    assert reconstruction_loss(E, ei, ew, 3, vo, "l1", include_identity=False,
                               include_within_view=False).item() == pytest.approx(1.0 / 4)


def _random_graph(sizes, d, seed, p_edge=0.4, dtype=D64):
    g = torch.Generator().manual_seed(seed)
    vo = np.concatenate([[0], np.cumsum(sizes)]).tolist()
    n = vo[-1]
    view = np.repeat(np.arange(len(sizes)), sizes)
    pairs, weights = [], []
    rng = np.random.default_rng(seed)
    for i in range(n):
        for j in range(i + 1, n):
            if view[i] != view[j] and rng.random() < p_edge:
                pairs.append((i, j))
                weights.append(float(rng.uniform(0.1, 1.0)))
    ei, ew = _edges(pairs, weights)
    E = torch.randn(n, d, generator=g, dtype=dtype)
    return E, ei, ew.to(dtype), vo, view


def _dense_reference(E, ei, ew, vo, view, kind, include_identity, include_within_view):
    n = E.shape[0]
    T = torch.zeros(n, n, dtype=E.dtype)
    T.index_put_((ei[0], ei[1]), ew, accumulate=True)
    if include_identity:
        T = T + torch.eye(n, dtype=E.dtype)
    diff = T - E @ E.t()
    diff = diff.abs() if kind == "l1" else diff.square()
    if include_within_view:
        return diff.mean()
    v = torch.as_tensor(view)
    mask = v[:, None] != v[None, :]
    if include_identity:
        mask = mask | torch.eye(n, dtype=torch.bool)
    return diff[mask].sum() / mask.sum()


@pytest.mark.parametrize("kind", ["l1", "l2"])
@pytest.mark.parametrize("include_identity", [True, False])
@pytest.mark.parametrize("include_within_view", [True, False])
def test_reconstruction_matches_dense_reference(kind, include_identity, include_within_view):
    for seed, sizes in [(0, [3, 4, 2]), (1, [5, 1, 0, 4]), (2, [6, 6])]:
        E, ei, ew, vo, view = _random_graph(sizes, 4, seed)
        got = reconstruction_loss(E, ei, ew, E.shape[0], vo, kind, include_identity, include_within_view)
        ref = _dense_reference(E, ei, ew, vo, view, kind, include_identity, include_within_view)
        assert torch.allclose(got, ref, rtol=1e-10, atol=1e-12), (seed, got, ref)


def test_reconstruction_float32_and_offsets_types():
    E, ei, ew, vo, view = _random_graph([3, 4, 2], 4, 3, dtype=torch.float32)
    a = reconstruction_loss(E, ei, ew, 9, torch.tensor(vo), "l1")
    b = reconstruction_loss(E, ei, ew, 9, np.array(vo), "l1")
    assert a.dtype == torch.float32 and torch.allclose(a, b)
    ref = _dense_reference(E.double(), ei, ew.double(), vo, view, "l1", True, True)
    assert abs(a.item() - ref.item()) < 1e-5


@pytest.mark.parametrize("kind", ["l1", "l2"])
@pytest.mark.parametrize("include_within_view", [True, False])
def test_reconstruction_gradcheck(kind, include_within_view):
    E, ei, ew, vo, _ = _random_graph([3, 2, 3], 3, 4)
    E.requires_grad_(True)
    f = lambda e: reconstruction_loss(e, ei, ew, 8, vo, kind, True, include_within_view)  # noqa: E731
    assert torch.autograd.gradcheck(f, (E,), eps=1e-6, atol=1e-7)


def test_reconstruction_bad_shapes():
    E, ei, ew, vo, _ = _random_graph([3, 2], 3, 5)
    with pytest.raises(ValueError, match=r"E: expected shape \(5, d\), got \(4, 3\)"):
        reconstruction_loss(E[:4], ei, ew, 5, vo)
    with pytest.raises(ValueError, match="view_offsets"):
        reconstruction_loss(E, ei, ew, 5, [0, 2, 4])
    with pytest.raises(ValueError, match=r"edge_weight: expected shape"):
        reconstruction_loss(E, ei, ew[:-1], 5, vo)
    with pytest.raises(ValueError, match="kind"):
        reconstruction_loss(E, ei, ew, 5, vo, kind="l3")


# ---------------------------------------------------------------------------
# Epipolar loss
# ---------------------------------------------------------------------------
def _one_hot(track, p):
    return torch.nn.functional.one_hot(torch.as_tensor(track), p).to(D64)


def test_epipolar_hand_computed_and_scale_free():
    # camera 0 at the origin, camera 1 at C = (s, 0, 0), both R = I: b̂ = (1, 0, 0)
    X = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.5, 1.0]], dtype=D64)
    E = torch.tensor([[1.0, 0.0], [1.0, 0.0]], dtype=D64)
    R = torch.eye(3, dtype=D64).expand(2, 3, 3)
    for s in (1.0, 10.0, 1e-3):
        t = torch.tensor([[0.0, 0.0, 0.0], [-s, 0.0, 0.0]], dtype=D64)  # t = -R C
        # x0 · (b̂ × x1) = (0,0,1) · (0, -1, 0.5) = 0.5
        assert epipolar_loss(E, X, R, t, [0, 1, 2]).item() == pytest.approx(0.5)
        r = epipolar_residuals(X[:1], X[1:], R[0], t[0], R[1], t[1])
        assert r.shape == (1,) and r.item() == pytest.approx(0.5)


def test_epipolar_loss_zero_for_true_matches_and_positive_for_wrong():
    rng = np.random.default_rng(0)
    for n_views in (2, 3):
        prob, X = _scene(rng, n_views=n_views)
        R, t = torch.from_numpy(prob.R), torch.from_numpy(prob.t)
        vo = prob.view_offsets
        E = _one_hot(prob.gt_track, 12)
        loss = epipolar_loss(E, torch.from_numpy(X), R, t, vo)
        assert loss.item() < 1e-12
        # from the float32 pixel keypoints via K^-1: tiny but not exactly zero
        Xk = torch.from_numpy(calibrated_points(prob))
        assert torch.allclose(Xk, torch.from_numpy(X), atol=1e-5)
        assert epipolar_loss(E, Xk, R, t, vo).item() < 1e-6
        # wrong matches: shuffle the track ids of the last view
        wrong = prob.gt_track.copy()
        sl = prob.view_slice(n_views - 1)
        wrong[sl] = np.roll(wrong[sl], 1)
        bad = epipolar_loss(_one_hot(wrong, 12), torch.from_numpy(X), R, t, vo)
        assert bad.item() > 1e-3


def test_epipolar_bad_shapes():
    X = torch.zeros(5, 3, dtype=D64)
    R, t = torch.eye(3, dtype=D64), torch.zeros(3, dtype=D64)
    with pytest.raises(ValueError, match=r"X_i: expected shape \(\*, N, 3\), got \(5, 2\)"):
        epipolar_residuals(X[:, :2], X, R, t, R, t)
    with pytest.raises(ValueError, match=r"R_j: expected shape \(\*, 3, 3\), got \(3, 2\)"):
        epipolar_residuals(X, X, R, t, R[:, :2], t)
    with pytest.raises(ValueError, match=r"t_i: expected shape \(\*, 3\), got \(2,\)"):
        epipolar_residuals(X, X, R, t[:2], R, t)
    E = torch.zeros(5, 2, dtype=D64)
    with pytest.raises(ValueError, match=r"R: expected shape \(2, 3, 3\)"):
        epipolar_loss(E, X, R.expand(3, 3, 3), t.expand(2, 3), [0, 2, 5])
    with pytest.raises(ValueError, match=r"X: expected shape \(5, 3\)"):
        epipolar_loss(E, X[:4], R.expand(2, 3, 3), t.expand(2, 3), [0, 2, 5])


def test_epipolar_gradcheck():
    rng = np.random.default_rng(2)
    prob, X = _scene(rng, n_views=3, p=4)
    E = torch.randn(12, 3, dtype=D64, requires_grad=True)
    args = (torch.from_numpy(X), torch.from_numpy(prob.R), torch.from_numpy(prob.t), prob.view_offsets)
    for clamp in (True, False):
        assert torch.autograd.gradcheck(lambda e: epipolar_loss(e, *args, clamp_negative=clamp), (E,),
                                        eps=1e-6, atol=1e-7)


def test_distillation_loss_known_answers():
    from gcn_match_ros.learn.losses import distillation_loss

    t = torch.tensor([-2.0, 0.0, 3.0])
    z = t.clone().requires_grad_(True)
    loss = distillation_loss(z, t)
    p = torch.sigmoid(t)
    entropy = -(p * p.log() + (1 - p) * (1 - p).log()).mean()
    assert loss.item() == pytest.approx(entropy.item(), rel=1e-6)  # the minimum: the teacher's entropy
    (g,) = torch.autograd.grad(loss, z)
    torch.testing.assert_close(g, torch.zeros(3), atol=1e-7, rtol=0)
    # elsewhere the gradient is (sigmoid(z) - p) / M, and the teacher gets none
    z2 = torch.zeros(3, requires_grad=True)
    t2 = t.clone().requires_grad_(True)
    (g2,) = torch.autograd.grad(distillation_loss(z2, t2), z2)
    torch.testing.assert_close(g2, (0.5 - p) / 3)
    assert distillation_loss(z2, t2).grad_fn is not None and t2.grad is None
    with pytest.raises(ValueError, match="differ in shape"):
        distillation_loss(torch.zeros(3), torch.zeros(4))
