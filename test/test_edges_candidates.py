"""Tests of gcn_match_ros.edges.candidates: candidate edge features checked against brute-force definitions."""
import numpy as np
import pytest

from gcn_match_ros.edges.candidates import (EDGE_FEATURES, RANK_CAP, CandidateJob, EdgeConfig, _deduplicated,
                                            _descriptor_features, _pair_block, _pair_candidates, _ranks, _triangle_support,
                                            candidate_edges, confident_pairs)
from gcn_match_ros.edges.verify import matrix_residuals
from gcn_match_ros.descriptors import cosine_distance, normalize_descriptors
from gcn_match_ros.similarity import most_similar
from gcn_match_ros.geometry import skew

from conftest import permuted_views_problem


def _brute_triangles(n_views, view, rows, cols, mask):
    nbrs = {}
    for r, c in zip(rows[mask], cols[mask]):
        nbrs.setdefault(r, set()).add(c)
        nbrs.setdefault(c, set()).add(r)
    out = []
    for r, c in zip(rows, cols):
        common = nbrs.get(r, set()) & nbrs.get(c, set())
        out.append(len({view[w] for w in common}) / (n_views - 2))
    return np.array(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_triangle_support_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    n_views, per_view = 5, 6
    view = np.repeat(np.arange(n_views), per_view)
    n = view.shape[0]
    a, b = rng.integers(0, n, size=(2, 150))
    keep = view[a] != view[b]
    rows, cols = np.minimum(a, b)[keep], np.maximum(a, b)[keep]
    mask = rng.random(rows.shape[0]) < 0.6
    got = _triangle_support(n, n_views, view, rows, cols, mask)
    np.testing.assert_allclose(got, _brute_triangles(n_views, view, rows, cols, mask))


def test_two_views_have_no_triangle_support():
    view = np.array([0, 0, 1, 1])
    assert np.all(_triangle_support(4, 2, view, np.array([0, 1]), np.array([2, 3]), np.ones(2, bool)) == 0)


def test_candidate_features_match_their_definitions():
    problem = permuted_views_problem(n_views=4, n_points=30, dim=32, noise=0.3, seed=3)
    es = candidate_edges(problem, EdgeConfig(k=3, geometry=False, guided=False))
    assert es.features.shape == (es.rows.shape[0], len(EDGE_FEATURES))
    assert np.all(es.rows < es.cols)
    assert np.all(problem.view_index[es.rows] != problem.view_index[es.cols])
    desc = normalize_descriptors(problem.descriptors, "rootsift")
    f = {name: es.features[:, i] for i, name in enumerate(EDGE_FEATURES)}
    offs = problem.view_offsets
    for e in range(es.rows.shape[0]):
        a, b = es.rows[e], es.cols[e]
        va, vb = problem.view_index[a], problem.view_index[b]
        row = desc[a] @ desc[offs[vb]:offs[vb + 1]].T   # a against every keypoint of b's view
        col = desc[b] @ desc[offs[va]:offs[va + 1]].T
        s = desc[a] @ desc[b]
        assert f["cosine"][e] == pytest.approx(s, abs=1e-5)
        rank_a, rank_b = int((row > s + 1e-6).sum()), int((col > s + 1e-6).sum())
        assert f["rank_a"][e] == pytest.approx(min(rank_a, RANK_CAP) / RANK_CAP)
        assert f["rank_b"][e] == pytest.approx(min(rank_b, RANK_CAP) / RANK_CAP)
        assert f["mutual"][e] == float(rank_a == 0 and rank_b == 0)
        # every candidate is among the top k of one of its ends
        assert rank_a < 3 or rank_b < 3
    # with moderate noise the true pairs are candidates
    true_pairs = set()
    for a in range(problem.n_keypoints):
        for b in range(a + 1, problem.n_keypoints):
            if problem.view_index[a] != problem.view_index[b] and problem.gt_track[a] == problem.gt_track[b]:
                true_pairs.add((a, b))
    found = set(zip(es.rows.tolist(), es.cols.tolist()))
    assert len(true_pairs & found) >= 0.9 * len(true_pairs)


def test_a_keep_rule_gives_the_kept_candidates_with_the_features_they_have_among_all():
    """Only the kept candidates get features, the same as among every candidate: their
    triangle support still counts through the candidates not kept. The rule is asked once a
    view pair, with its candidates and model."""
    problem = permuted_views_problem(n_views=4, n_points=40, dim=32, noise=0.3, seed=5)
    config = EdgeConfig(k=3, geometry=False, guided=False)
    every = candidate_edges(problem, config)
    offs = problem.view_offsets
    seen = {}

    def keep(pair, model, part):
        i, j = pair
        seen[pair] = model
        return (part.ea + offs[i] + part.eb + offs[j]) % 3 == 0

    job = CandidateJob(problem, config, keep=keep)
    kept = job.result()
    assert seen == every.models and job.candidates == every.rows.shape[0]
    wanted = every.subset((every.rows + every.cols) % 3 == 0)
    assert 0 < kept.rows.shape[0] < every.rows.shape[0]
    tri = [EDGE_FEATURES.index("tri_all"), EDGE_FEATURES.index("tri_conf")]
    assert wanted.features[:, tri].any()  # the check below reads some triangles
    for field in ("rows", "cols", "features", "res_px", "confident"):
        np.testing.assert_array_equal(getattr(kept, field), getattr(wanted, field))


def test_no_candidates_for_single_keypoint_views():
    problem = permuted_views_problem(n_views=3, n_points=1, dim=8)
    es = candidate_edges(problem)
    assert es.rows.shape == (0,) and es.features.shape == (0, len(EDGE_FEATURES))


def test_geometry_falls_back_to_mutual_seeds_when_the_ratio_test_leaves_too_few():
    """Generated SIFT-like descriptors fail Lowe's ratio test almost everywhere; the two-view
    models are then fitted on mutual nearest neighbours, so view pairs still get trusted ones."""
    from gcn_match_ros.data import synthetic

    problem = synthetic.random_scene_problem(synthetic.rome16k(3), np.random.default_rng([5, 0]))
    es = candidate_edges(problem)
    f = {name: es.features[:, i] for i, name in enumerate(EDGE_FEATURES)}
    assert f["confident"].sum() < 3 * 12   # fewer than MIN_SEEDS survivors per pair on average
    trusted = [m for m in es.models.values() if m is not None]
    assert len(trusted) >= 2 and all(m.trusted() for m in trusted)  # yet most pairs have a trusted model
    assert f["has_model"].max() == 1.0 and f["guided"].sum() > 0


def test_only_trusted_models_give_geometric_features_and_guided_candidates():
    """Two views of a 3-D scene: with calibrated cameras an essential matrix is fitted and
    trusted; asking for more inliers than there are seeds leaves the pair without a model,
    its candidates without geometric credit and without guided ones."""
    from gcn_match_ros.data import synthetic

    problem = synthetic.random_scene_problem(synthetic.preset("easy", 2, "sift"), np.random.default_rng(3))
    es = candidate_edges(problem)
    model = es.models[(0, 1)]
    assert model is not None and model.trusted() and model.essential
    f = {name: es.features[:, i] for i, name in enumerate(EDGE_FEATURES)}
    assert f["has_model"].min() == 1.0 and f["guided"].sum() > 0 and np.isfinite(es.res_px).all()
    strict = candidate_edges(problem, EdgeConfig(min_inliers=10_000))
    g = {name: strict.features[:, i] for i, name in enumerate(EDGE_FEATURES)}
    assert strict.models == {(0, 1): None}
    assert g["has_model"].max() == 0.0 and g["guided"].sum() == 0 and np.isinf(strict.res_px).all()
    uncalibrated = candidate_edges(problem, EdgeConfig(essential=False)).models[(0, 1)]
    assert uncalibrated is not None and not uncalibrated.essential


def test_noise_scaled_residuals_are_in_units_of_the_noise_of_pairs_without_sub_pixel_keypoints():
    """Two views of a 3-D scene: with 1 px of keypoint noise the pair's model is fitted at
    epipolar_px and, with noise_scaled_residuals, its residual features are those of the pixel
    residuals over noise_px / AGREE_MIN_PX (> 1); the edges, their pixel residuals and every
    other feature stay. With 0.6 px the model is fitted at epipolar_px too, but its measured
    sigma (noise_px / 3: 0.45 px) is within fine_px, and with 0.1 px the fine fit is kept: there
    nothing changes."""
    import dataclasses

    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges.verify import AGREE_MIN_PX, EPIPOLAR_PX

    res = [EDGE_FEATURES.index("res_log"), EDGE_FEATURES.index("res_lin")]
    for pixel_noise, coarse, scaled in ((1.0, True, True), (0.6, True, False), (0.1, False, False)):
        scene = dataclasses.replace(synthetic.preset("easy", 2, "sift"), pixel_noise=pixel_noise)
        problem = synthetic.random_scene_problem(scene, np.random.default_rng(3))
        px = candidate_edges(problem)
        units = candidate_edges(problem, EdgeConfig(noise_scaled_residuals=True))
        model = units.models[(0, 1)]
        assert (model.epipolar_fit_px == EPIPOLAR_PX) == coarse
        np.testing.assert_array_equal(units.rows, px.rows)
        np.testing.assert_array_equal(units.res_px, px.res_px)
        others = [i for i in range(len(EDGE_FEATURES)) if i not in res]
        np.testing.assert_array_equal(units.features[:, others], px.features[:, others])
        expected = px.features[:, res]
        if scaled:
            unit = model.noise_px / AGREE_MIN_PX
            assert unit > 1.5
            d = px.res_px / unit
            expected = np.stack([np.log1p(np.minimum(d, 1e3)) / np.log1p(1e3), np.minimum(d, 10.0) / 10.0], axis=1)
        np.testing.assert_allclose(units.features[:, res], expected, rtol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_deduplicated_candidates_are_the_sorted_unique_pairs_guided_if_any_copy_is(seed):
    rng = np.random.default_rng(seed)
    na, nb = 40, 30
    ea, eb = rng.integers(0, na, 300), rng.integers(0, nb, 300)  # many copies
    guided = rng.random(300) < 0.3
    a, b, g = _deduplicated(ea, eb, guided, na, nb)
    keys, first = np.unique(ea * nb + eb, return_inverse=True)
    np.testing.assert_array_equal(a * nb + b, keys)
    np.testing.assert_array_equal(g, np.bincount(first, weights=guided, minlength=keys.size) > 0)
    empty = _deduplicated(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool), na, nb)
    assert all(x.size == 0 for x in empty)


@pytest.mark.parametrize("seed", [0, 1])
def test_descriptor_features_are_numpys_float32_arithmetic_bit_for_bit(seed):
    """The compiled features equal the numpy expressions they replaced: ranks from the best
    lists, Lowe ratios in float32 (cosine distance to the candidate over that to the best other
    keypoint), mutual and confident flags, all capped."""
    rng = np.random.default_rng(seed)
    sim = rng.uniform(-0.2, 1.0, (50, 45)).astype(np.float32)
    sim[3, 7] = sim[3, 8] = sim[3].max()  # a tie at the top of a row
    top_r, _, top_c, _ = most_similar(sim, RANK_CAP + 1, RANK_CAP + 1)
    ea, eb = np.divmod(np.unique(rng.integers(0, 50 * 45, 900)), 45)
    ea, eb = np.r_[ea, 3, 3], np.r_[eb, 7, 8]
    got = _descriptor_features(sim, top_r, top_c, ea, eb, 0.8)
    s = sim[ea, eb]
    rank_a, rank_b = _ranks(top_r, ea, s), _ranks(top_c, eb, s)
    rat_a = cosine_distance(s) / np.maximum(np.where(rank_a == 0, cosine_distance(top_r[ea, 1]),
                                                     cosine_distance(top_r[ea, 0])), 1e-9)
    rat_b = cosine_distance(s) / np.maximum(np.where(rank_b == 0, cosine_distance(top_c[eb, 1]),
                                                     cosine_distance(top_c[eb, 0])), 1e-9)
    mutual = (rank_a == 0) & (rank_b == 0)
    want = (s, np.minimum(rank_a, RANK_CAP), np.minimum(rank_b, RANK_CAP), np.minimum(rat_a, 1.5),
            np.minimum(rat_b, 1.5), mutual, mutual & (rat_a < 0.8) & (rat_b < 0.8))
    for g, w in zip(got, want):
        assert g.dtype == w.dtype
        np.testing.assert_array_equal(g, w)
    assert got[5].any() and got[6].any() and (got[1] == RANK_CAP).any()  # every case occurs


@pytest.mark.parametrize("seed", [0, 1])
def test_confident_pairs_are_numpys_float32_arithmetic_bit_for_bit(seed):
    """The compiled seeds equal the numpy expressions they replaced: mutual nearest neighbours whose
    float32 Lowe ratios from both sides are below the ratio, compared in float32."""
    rng = np.random.default_rng(seed)
    sim = rng.uniform(-0.2, 1.0, (60, 50)).astype(np.float32)
    top_r, ir, top_c, ic = most_similar(sim, 2, 2)
    for ratio in (0.8, 0.95, float(np.float32(0.9)) + 1e-12):
        seeds, partners, mutual = confident_pairs(top_r, ir, top_c, ic, ratio)
        nn_r = ir[:, 0]
        want_mutual = ic[nn_r, 0] == np.arange(60)
        ratio_r = cosine_distance(top_r[:, 0]) / np.maximum(cosine_distance(top_r[:, 1]), 1e-9)
        ratio_c = cosine_distance(top_c[:, 0]) / np.maximum(cosine_distance(top_c[:, 1]), 1e-9)
        want = np.flatnonzero(want_mutual & (ratio_r < ratio) & (ratio_c[nn_r] < ratio))
        np.testing.assert_array_equal(mutual, want_mutual)
        np.testing.assert_array_equal(seeds, want)
        np.testing.assert_array_equal(partners, nn_r[want])
        assert seeds.dtype == partners.dtype == np.int64
    assert seeds.size and (~mutual).any()


@pytest.mark.parametrize("seed", [0, 1])
def test_pair_candidates_are_the_steps_they_fuse(seed):
    """One view pair's compiled candidates equal its steps one by one: each keypoint's k best in
    the other view and the guided pairs, deduplicated, their descriptor features and their
    residuals under H and F (inf where the model has none)."""
    rng = np.random.default_rng(seed)
    na, nb, k = 40, 35, 3
    sim = rng.uniform(-0.2, 1.0, (na, nb)).astype(np.float32)
    top_r, ir, top_c, ic = most_similar(sim, RANK_CAP + 1, RANK_CAP + 1)
    xa, xb = rng.uniform(0, 640, (na, 2)), rng.uniform(0, 480, (nb, 2))
    ga, gb = rng.integers(0, na, 25), rng.integers(0, nb, 25)
    H = np.eye(3) + rng.normal(0, 1e-3, (3, 3))
    F = rng.normal(0, 1e-3, (3, 3))
    ea = np.concatenate([np.repeat(np.arange(na), k), ic[:, :k].ravel(), ga])
    eb = np.concatenate([ir[:, :k].ravel(), np.repeat(np.arange(nb), k), gb])
    guided = np.r_[np.zeros((na + nb) * k, bool), np.ones(25, bool)]
    want_a, want_b, want_guided = _deduplicated(ea, eb, guided, na, nb)
    want_features = _descriptor_features(sim, top_r, top_c, want_a, want_b, 0.8)
    for has_h, has_f in ((True, True), (False, True), (True, False), (False, False)):
        got = _pair_candidates(sim, top_r, ir, top_c, ic, k, ga, gb, 0.8, xa, xb, H, np.linalg.inv(H), F, has_h, has_f)
        want_res = matrix_residuals(xa[want_a], xb[want_b], H, np.linalg.inv(H), F, has_h, has_f)
        for g, w in zip(got, (want_a, want_b, want_guided) + want_features + want_res):
            assert g.dtype == w.dtype
            np.testing.assert_array_equal(g, w)
    assert np.isinf(got[-1]).all() and want_guided.any()


def test_a_pair_block_holds_the_kept_candidates_columns_as_numpy_casts_them():
    """The per-pair columns of the kept candidates' feature rows are numpy's float32 casts of
    the float64 values (ranks / RANK_CAP, flags, the model kind); the window's columns are left
    for the assembly; every candidate comes back in global indices."""
    rng = np.random.default_rng(0)
    m = 200
    ea, eb = rng.integers(0, 50, m), rng.integers(0, 40, m)
    conf, kept, mutual, guided = (rng.random(m) < q for q in (0.2, 0.6, 0.3, 0.1))
    cosine, ratio_a, ratio_b = (rng.random(m).astype(np.float32) for _ in range(3))
    rank_a, rank_b = rng.integers(0, RANK_CAP + 1, m), rng.integers(0, RANK_CAP + 1, m)
    res_h, res_f = rng.exponential(3.0, m), rng.exponential(3.0, m)
    for kind in (0.0, 1.0, 2.0):
        rows, cols, conf_all, kept_rows, kept_cols, features, res_px = _pair_block(
            ea, eb, conf, kept, 100, 300, cosine, ratio_a, ratio_b, rank_a, rank_b, mutual, kind, guided, res_h, res_f)
        np.testing.assert_array_equal(rows, ea + 100)
        np.testing.assert_array_equal(cols, eb + 300)
        np.testing.assert_array_equal(conf_all, conf)
        np.testing.assert_array_equal(kept_rows, rows[kept])
        np.testing.assert_array_equal(kept_cols, cols[kept])
        np.testing.assert_array_equal(res_px, np.minimum(res_h, res_f)[kept])
        want = {"cosine": cosine, "ratio_a": ratio_a, "ratio_b": ratio_b,
                "rank_a": rank_a.astype(np.float64) / RANK_CAP, "rank_b": rank_b.astype(np.float64) / RANK_CAP,
                "mutual": mutual, "confident": conf, "has_model": np.full(m, float(kind > 0)),
                "planar": np.full(m, float(kind == 2)), "guided": guided}
        expected = np.zeros((kept.sum(), len(EDGE_FEATURES)), np.float32)
        for name, column in want.items():
            expected[:, EDGE_FEATURES.index(name)] = column[kept]
        assert features.dtype == np.float32
        np.testing.assert_array_equal(features, expected)


def _dense_best_near_lines(sim, F, xa, xb, px):
    """The rule of candidates._best_near_lines from the distance matrix and a masked argmax."""
    from gcn_match_ros.geometry import epipolar_distance_matrix

    masked = np.where(epipolar_distance_matrix(F, xa, xb) < px, sim, -np.inf)
    return (np.where(np.isfinite(masked.max(1)), masked.argmax(1), -1),
            np.where(np.isfinite(masked.max(0)), masked.argmax(0), -1))


# Epipolar geometries of b: lines that do not meet in one point (a general matrix), an epipole
# far outside the image (cameras side by side), one inside it (a camera moving forwards: keypoints
# around it in every direction), and parallel lines (a rectified stereo pair).
_GEOMETRIES = {
    "general": np.array([[0, -1e-3, 0.2], [1e-3, 0, -0.3], [-0.2, 0.3, 1.0]]),
    "epipole outside": skew(np.array([2500.0, -900.0, 1.0])),
    "epipole inside": skew(np.array([320.0, 300.0, 1.0])),
    "parallel lines": skew(np.array([1.0, 0.0, 0.0])),
}


@pytest.mark.parametrize("geometry", sorted(_GEOMETRIES))
def test_epipolar_guided_candidates_follow_the_dense_rule(geometry):
    """The compiled pass gives, per keypoint, the most similar keypoint of the other view within
    px of both epipolar lines — what the distance matrix and a masked argmax give — whether the
    lines meet inside the image, far outside it, nowhere (parallel) or not in one point."""
    from gcn_match_ros.edges.candidates import _best_near_lines
    from gcn_match_ros.geometry import homogeneous

    F = _GEOMETRIES[geometry]
    rng = np.random.default_rng(7)
    xa, xb = rng.uniform(0, 640, (300, 2)), rng.uniform(0, 640, (320, 2))
    sim = rng.random((300, 320)).astype(np.float32)
    sim[:, 5] = sim[:, 6]  # ties: the first keypoint, as argmax
    sim[::7] = np.round(sim[::7] * 4) / 4  # rows of many ties
    found = []
    for px in (0.5, 3.0, 40.0, 200.0):
        j, i = _best_near_lines(sim, homogeneous(xa) @ F.T, homogeneous(xb) @ F, xa, xb, px)
        found.append(int((j >= 0).sum()))
        want_j, want_i = _dense_best_near_lines(sim, F, xa, xb, px)
        np.testing.assert_array_equal(j, want_j)
        np.testing.assert_array_equal(i, want_i)
    assert 0 < found[1] < 300 and found[0] <= found[1] <= found[2] <= found[3]  # the tolerance matters


def test_edge_config_fits_and_trusts_with_its_own_settings():
    """EdgeConfig.fit is fit_pair at the config's thresholds (an essential matrix only when
    asked for); EdgeConfig.trusted applies the config's trust rule and keeps the selected model."""
    from test_edges_verify import K, _non_planar_pairs

    xa, xb, _ = _non_planar_pairs(np.random.default_rng(4))
    assert EdgeConfig().fit(xa, xb, K, K).essential
    assert not EdgeConfig(essential=False).fit(xa, xb, K, K).essential
    model = EdgeConfig().fit(xa, xb, K, K)
    trusted = EdgeConfig().trusted(model)
    assert trusted is not None and trusted.H is None and trusted.F is not None  # F selected
    assert EdgeConfig(min_inliers=len(xa) + 1).trusted(model) is None
    assert EdgeConfig().trusted(None) is None
    from test_edges_verify import _plane_and_off_plane_pairs

    xa, xb = _plane_and_off_plane_pairs(np.random.default_rng(5))
    assert not EdgeConfig().fit(xa, xb).planar and EdgeConfig(planar_ratio=0.7).fit(xa, xb).planar
    with pytest.raises(ValueError, match="planar_ratio"):
        EdgeConfig(planar_ratio=0.0)


def test_a_candidate_job_shared_by_two_threads_gives_the_one_thread_edges(monkeypatch):
    """Four calibrated views, six view pairs: a second thread helping with the pairs changes
    nothing; every pair is computed once; a pair's error reaches the thread asking for the result."""
    import threading

    from gcn_match_ros.data import synthetic
    from gcn_match_ros.edges import candidates as cand
    from gcn_match_ros.edges.rig_memory import RigMemory

    problem = synthetic.random_scene_problem(synthetic.preset("easy", 4, "sift"), np.random.default_rng(5))
    problem.camera_ids = tuple(f"cam{v}" for v in range(4))
    alone = cand.candidate_edges(problem)
    rig = RigMemory()
    job = cand.CandidateJob(problem, rig=rig)
    helper = threading.Thread(target=job.help)
    helper.start()
    shared = job.result()
    helper.join()
    for field in ("rows", "cols", "features", "res_px", "confident"):
        np.testing.assert_array_equal(getattr(shared, field), getattr(alone, field))
    assert shared.models.keys() == alone.models.keys() and rig.fitted == 6  # each pair once

    calls = []

    def failing(job, i, j):
        calls.append((i, j))
        raise RuntimeError(f"pair {i}, {j}")

    monkeypatch.setattr(cand.CandidateJob, "_pair", failing)
    with pytest.raises(RuntimeError, match="pair 2, 3"):
        cand.CandidateJob(problem).result()
    assert calls == [(2, 3)]  # taken from the last pair; none after an error


def test_rank_counts_the_strictly_better_entries_of_its_keypoints_list():
    """A candidate's rank is how many of its keypoint's best values beat it: equal values do not
    (the list's own entry ranks where it stands), and below the list the rank is its length."""
    top = np.array([[0.9, 0.8, 0.5], [0.7, 0.6, 0.6]], np.float32)
    at = np.array([0, 0, 0, 1, 1])
    s = np.array([0.95, 0.8, 0.1, 0.6, 0.65], np.float32)
    np.testing.assert_array_equal(_ranks(top, at, s), [0, 1, 3, 1, 1])
    np.testing.assert_array_equal(_ranks(top, at, s), (top[at] > s[:, None]).sum(1))
