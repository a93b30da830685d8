"""Tests of gcn_match_ros.data.synthetic: generated multi-view scenes and the batch writer."""
import itertools

import numpy as np
import pytest

from gcn_match_ros.data.permutation_noise import permutation_noise_problem
from gcn_match_ros.data.synthetic import (SceneConfig, easy, mutual_nn_prf, partial, random_scene_problem, rome16k,
                                          sift_normalize, write_problems)
from gcn_match_ros.problem import load_problem

from conftest import same_problem as _same, true_pair_set as _true_pairs


V_MAX = 1000


CONFIGS = {
    "rome16k3": rome16k(3),
    "rome16k4": rome16k(4),
    "partial3": partial(3),
    "easy": easy(3),
    "forward": rome16k(4, layout="forward"),
    "gaussian": partial(5, descriptor_kind="gaussian", descriptor_dim=32),
    "singletons": partial(3, min_views=1, visibility=0.4),
    "binary": partial(3, descriptor_kind="binary"),
}


# --- scene generator -------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_scene_deterministic(name):
    cfg = CONFIGS[name]
    a, b = random_scene_problem(cfg, 7), random_scene_problem(cfg, np.random.default_rng(7))
    assert _same(a, b)
    assert not _same(a, random_scene_problem(cfg, 8))


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_scene_shapes_and_ranges(name, tmp_path):
    from gcn_match_ros.problem import save_problem
    cfg = CONFIGS[name]
    prob = random_scene_problem(cfg, 3)
    save_problem(prob, tmp_path / "p.npz")
    back = load_problem(tmp_path / "p.npz")  # validates
    assert _same(prob, back)
    n, V = prob.n_keypoints, cfg.n_views
    assert prob.n_views == V
    assert prob.keypoints.dtype == np.float32 and prob.keypoints.shape == (n, 2)
    assert prob.descriptors.dtype == np.float32 and prob.descriptors.shape == (n, cfg.descriptor_dim)
    assert prob.gt_track.dtype == np.int64 and prob.K.shape == (V, 3, 3) and prob.R.shape == (V, 3, 3)
    w, h = cfg.image_size
    assert np.all(prob.keypoints >= 0) and np.all(prob.keypoints[:, 0] <= w - 1)
    assert np.all(prob.keypoints[:, 1] <= h - 1)
    assert np.all(prob.image_size == [w, h])
    if cfg.descriptor_kind == "binary":
        assert set(np.unique(prob.descriptors)) <= {0.0, 1.0}
    else:
        np.testing.assert_allclose(np.linalg.norm(prob.descriptors, axis=1), 1.0, atol=1e-5)
    if cfg.descriptor_kind == "sift":
        assert prob.descriptors.min() >= 0.0
    assert np.all(prob.scales > 0) and np.all(np.abs(prob.orientations) <= np.pi + 1e-6)
    for R in prob.R:
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_scene_tracks_well_formed(name):
    cfg = CONFIGS[name]
    prob = random_scene_problem(cfg, 11)
    gt, view = prob.gt_track, prob.view_index
    ids = gt[gt >= 0]
    # at most one keypoint per view per track, every track in >= 2 views
    assert np.unique(ids * V_MAX + view[gt >= 0]).size == ids.size
    _, counts = np.unique(ids, return_counts=True)
    assert np.all(counts >= 2) and np.all(counts <= cfg.n_views)
    assert np.all(gt >= -1)


def test_full_visibility_everyone_sees_everything():
    prob = random_scene_problem(rome16k(4), 0)
    assert np.all(prob.view_sizes == 80)
    for v in range(4):
        assert sorted(prob.gt_track[prob.view_slice(v)]) == list(range(80))
    # views are shuffled: not stored in point order
    assert not np.array_equal(prob.gt_track[prob.view_slice(0)], np.arange(80))


def test_distractors_get_minus_one():
    cfg = partial(3)
    prob = random_scene_problem(cfg, 5)
    for v in range(3):
        g = prob.gt_track[prob.view_slice(v)]
        # min_views = 2: every real keypoint has a track, so the -1 are exactly the distractors
        n_real = int(np.sum(g >= 0))
        assert int(np.sum(g == -1)) == round(cfg.distractor_fraction / (1 - cfg.distractor_fraction) * n_real)
    # points seen once (min_views = 1) also get -1, and no distractors then means -1 = singletons
    prob = random_scene_problem(partial(3, min_views=1, visibility=0.3, distractor_fraction=0.0), 5)
    assert np.any(prob.gt_track == -1)
    ids, counts = np.unique(prob.gt_track[prob.gt_track >= 0], return_counts=True)
    assert np.all(counts >= 2)


def test_noiseless_descriptors_mutual_nn_exact():
    for cfg in (rome16k(3, descriptor_noise=0.0), rome16k(4, descriptor_kind="gaussian", descriptor_noise=0.0)):
        prob = random_scene_problem(cfg, 2)
        p, r, f1, tp, pred, true = mutual_nn_prf(prob)
        assert tp == pred == true == 80 * cfg.n_views * (cfg.n_views - 1) // 2
    # with partial visibility and distractors every true pair is still found (recall 1)
    prob = random_scene_problem(partial(4, descriptor_noise=0.0), 2)
    assert mutual_nn_prf(prob)[1] == 1.0


def test_mutual_nn_prf_matches_bruteforce():
    prob = random_scene_problem(partial(3), 4)
    d = prob.descriptors / np.linalg.norm(prob.descriptors, axis=1, keepdims=True)
    view = prob.view_index
    S = d @ d.T
    pred = set()
    for i, j in itertools.combinations(range(3), 2):
        si, sj = prob.view_slice(i), prob.view_slice(j)
        B = S[si, sj]
        for r in range(B.shape[0]):
            c = int(B[r].argmax())
            if int(B[:, c].argmax()) == r:
                pred.add((si.start + r, sj.start + c))
    true = _true_pairs(prob.gt_track, view)
    p, r, _, tp, npred, ntrue = mutual_nn_prf(prob)
    assert (tp, npred, ntrue) == (len(pred & true), len(pred), len(true))


@pytest.mark.parametrize("layout", ["orbit", "forward"])
def test_epipolar_constraint_exact(layout):
    cfg = rome16k(4, layout=layout, pixel_noise=0.0, visibility=0.8)
    prob = random_scene_problem(cfg, 9)
    Kinv = np.linalg.inv(prob.K)
    x = np.concatenate([prob.keypoints.astype(np.float64), np.ones((prob.n_keypoints, 1))], axis=1)
    view = prob.view_index
    xc = np.einsum("nij,nj->ni", Kinv[view], x)  # calibrated homogeneous points
    pairs = np.array(sorted(_true_pairs(prob.gt_track, view)))
    rng = np.random.default_rng(0)
    worst, false_res = 0.0, []
    for i, j in itertools.permutations(range(4), 2):
        Rij = prob.R[j] @ prob.R[i].T
        tij = prob.t[j] - Rij @ prob.t[i]
        tij = tij / np.linalg.norm(tij)
        tx = np.array([[0, -tij[2], tij[1]], [tij[2], 0, -tij[0]], [-tij[1], tij[0], 0]])
        E = tx @ Rij
        sel = pairs[(view[pairs[:, 0]] == i) & (view[pairs[:, 1]] == j)]
        sel = np.concatenate([sel, pairs[(view[pairs[:, 0]] == j) & (view[pairs[:, 1]] == i)][:, ::-1]])
        res = np.abs(np.einsum("ni,ij,nj->n", xc[sel[:, 1]], E, xc[sel[:, 0]]))
        worst = max(worst, res.max())
        a = rng.choice(np.flatnonzero(view == i), 50)
        b = rng.choice(np.flatnonzero(view == j), 50)
        false_res.append(np.abs(np.einsum("ni,ij,nj->n", xc[b], E, xc[a])))
    assert worst < 1e-6
    assert np.median(np.concatenate(false_res)) > 1e-3  # the check is not vacuous


def _triangulate(P1, P2, x1, x2):
    """Linear (DLT) triangulation of one point from two 3x4 projection matrices."""
    A = np.stack([x1[0] * P1[2] - P1[0], x1[1] * P1[2] - P1[1], x2[0] * P2[2] - P2[0], x2[1] * P2[2] - P2[1]])
    X = np.linalg.svd(A)[2][-1]
    return X[:3] / X[3]


@pytest.mark.parametrize("layout", ["orbit", "forward"])
def test_reprojection_depth_scales_orientations(layout):
    cfg = rome16k(3, layout=layout, scale_view_log_std=0.0, orientation_noise_deg=0.0, roll_deg=0.0,
                  pixel_noise=0.0)
    prob = random_scene_problem(cfg, 1)
    V, P = 3, 80
    kp = np.zeros((V, P, 2)); s = np.zeros((V, P)); o = np.zeros((V, P))
    for v in range(V):
        sl = prob.view_slice(v)
        g = prob.gt_track[sl]
        kp[v, g], s[v, g], o[v, g] = prob.keypoints[sl], prob.scales[sl], prob.orientations[sl]
    Pm = [prob.K[v] @ np.concatenate([prob.R[v], prob.t[v][:, None]], axis=1) for v in range(V)]
    for p in range(P):
        X = _triangulate(Pm[0], Pm[1], kp[0, p], kp[1, p])
        depth = np.array([(prob.R[v] @ X + prob.t[v])[2] for v in range(V)])
        assert np.all(depth > 0)  # in front of every camera that sees it
        x2 = Pm[2] @ np.append(X, 1.0)
        np.testing.assert_allclose(x2[:2] / x2[2], kp[2, p], atol=2e-3)  # reprojects into view 2
        # scale ∝ 1 / depth (no per-view scale noise here)
        np.testing.assert_allclose(s[:, p] * depth, s[0, p] * depth[0], rtol=1e-4)
    # no roll, no orientation noise: every observation of a point has the same orientation
    np.testing.assert_allclose(o[1:], np.broadcast_to(o[0], (2, P)), atol=1e-5)


def test_config_validation():
    with pytest.raises(ValueError):
        SceneConfig(layout="spiral")
    with pytest.raises(ValueError):
        SceneConfig(distractor_fraction=1.0)
    with pytest.raises(ValueError):
        SceneConfig(descriptor_kind="orb")
    with pytest.raises(ValueError, match="bit-flip probability"):
        SceneConfig(descriptor_kind="binary", descriptor_dim=256, descriptor_noise=1.2)


def test_binary_descriptors_are_orb_like_codes():
    prob = random_scene_problem(rome16k(3, descriptor_kind="binary", distractor_fraction=0.3), 5)
    d = prob.descriptors
    assert d.shape[1] == 256 and set(np.unique(d)) == {0.0, 1.0}
    from gcn_match_ros.descriptors import descriptor_kind
    assert descriptor_kind(d) == (256, True)  # the gcn solver would pick the ORB model
    # two observations of a point differ in each bit with probability 2 f (1 - f), f = 0.28;
    # unrelated codes (distractors) in half of the bits
    gt, view = prob.gt_track, prob.view_index
    same = np.array([np.abs(d[a] - d[b]).mean() for a, b in _true_pairs(gt, view)])
    np.testing.assert_allclose(same.mean(), 2 * 0.28 * 0.72, atol=0.01)
    lone = np.flatnonzero(gt == -1)
    a, b = lone[view[lone] == 0], lone[view[lone] == 1]
    np.testing.assert_allclose(np.abs(d[a][:, None] - d[b][None]).mean(), 0.5, atol=0.01)


def test_sift_normalize():
    d = sift_normalize(np.array([[10.0, 1.0, 1.0, 0.0], [0.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(np.linalg.norm(d[0]), 1.0, rtol=1e-6)
    assert np.all(d[1] == 0)
    assert d[0, 0] < 0.99  # the dominant bin was clipped


def test_presets_difficulty_quick():
    # a few problems only (the documented numbers use 200); loose bounds
    def f1(cfg):
        tp = pred = true = 0
        for s in range(12):
            _, _, _, a, b, c = mutual_nn_prf(random_scene_problem(cfg, s))
            tp, pred, true = tp + a, pred + b, true + c
        p, r = tp / pred, tp / true
        return 2 * p * r / (p + r)
    assert 0.65 < f1(rome16k(3)) < 0.85
    assert f1(easy(3)) > 0.95
    assert 0.6 < f1(partial(3)) < 0.85
    assert 0.65 < f1(rome16k(3, descriptor_kind="binary")) < 0.85
    assert 0.6 < f1(partial(3, descriptor_kind="binary")) < 0.85


# --- batch writer ---------------------------------------------------------------------------
def test_write_problems_deterministic(tmp_path):
    gen = lambda rng: random_scene_problem(partial(3), rng)  # noqa: E731
    p1 = write_problems(tmp_path / "a", gen, 3, seed=42, prefix="part")
    p2 = write_problems(tmp_path / "b", gen, 3, seed=42, prefix="part", progress=False)
    p3 = write_problems(tmp_path / "c", gen, 2, seed=43, prefix="part", progress=False)
    assert [p.name for p in p1] == ["part-00000.npz", "part-00001.npz", "part-00002.npz"]
    for a, b in zip(p1, p2):
        assert _same(load_problem(a), load_problem(b))
    assert not _same(load_problem(p1[0]), load_problem(p1[1]))
    assert not _same(load_problem(p1[0]), load_problem(p3[0]))
    # a tuple-returning generator (the permutation protocol) is accepted
    p4 = write_problems(tmp_path / "d", lambda rng: permutation_noise_problem(3, rng=rng), 2, seed=0,
                        prefix="perm", progress=False)
    assert load_problem(p4[1]).n_keypoints == 75
