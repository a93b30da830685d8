"""Tests of gcn_match_ros.edges.verify: two-view models fitted on seed pairs, and their residuals."""
import numpy as np
import pytest

from gcn_match_ros import geometry
from gcn_match_ros.data import synthetic
from gcn_match_ros.edges import verify
from gcn_match_ros.edges.candidates import candidate_edges
from gcn_match_ros.edges.verify import AGREE_MIN_PX, EPIPOLAR_PX, FINE_PX, MIN_INLIER_RATIO, RANSAC_PX, MIN_INLIERS, MIN_SEEDS, PairModel, check_planar_ratio, fit_pair, may_be_trusted, residuals
from gcn_match_ros.solvers.gcn import GCNSolver

from conftest import look_at, true_pair_list

H_TRUE = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [2e-4, -1e-4, 1.0]])
K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])


def _two_cameras():
    """(R_a, t_a, R_b, t_b): two cameras 10 m from the origin, 20 deg apart, looking at it."""
    angle = np.radians(20)
    return (*look_at(np.array([0.0, -10, 0.5]), np.zeros(3)),
            *look_at(np.array([10 * np.sin(angle), -10 * np.cos(angle), 1.0]), np.zeros(3)))


def _non_planar_pairs(rng, n=60):
    """Pixels of n points of a 6 m cube in the two cameras, and their true F."""
    R_a, t_a, R_b, t_b = _two_cameras()
    X = rng.uniform(-3, 3, (n, 3))
    xa, xb = geometry.project(K, R_a, t_a, X)[0], geometry.project(K, R_b, t_b, X)[0]
    return xa, xb, geometry.fundamental_from_poses(K, R_a, t_a, K, R_b, t_b)


def test_points_related_by_a_homography_give_a_planar_model():
    rng = np.random.default_rng(0)
    xa = rng.uniform(0, 640, (40, 2))
    xb = geometry.transfer(H_TRUE, xa)
    model = fit_pair(xa, xb)
    assert model is not None and model.planar and model.H is not None
    np.testing.assert_allclose(model.H / model.H[2, 2], H_TRUE, atol=1e-2)
    res_h, _ = residuals(model, xa, xb)
    assert res_h.max() < 1e-2  # pixels: exact data, up to the estimator's own precision (~1e-4)
    selected = model.selected()
    assert selected.planar and selected.F is None and selected.H is model.H


def test_points_of_a_3d_scene_give_a_fundamental_matrix():
    rng = np.random.default_rng(1)
    xa, xb, F_true = _non_planar_pairs(rng)
    model = fit_pair(xa, xb)
    assert model is not None and not model.planar and model.F is not None
    _, res_f = residuals(model, xa, xb)
    assert res_f.max() < 1e-2
    F, G = model.F / np.linalg.norm(model.F), F_true / np.linalg.norm(F_true)
    np.testing.assert_allclose(F * np.sign(np.sum(F * G)), G, atol=1e-5)  # the same F, up to scale
    assert model.selected().H is None


def _plane_and_off_plane_pairs(rng):
    """Pixels of 30 points of a plane and 10 points 2 m off it in the two cameras."""
    R_a, t_a, R_b, t_b = _two_cameras()
    plane = np.c_[rng.uniform(-3, 3, 30), np.zeros(30), rng.uniform(-3, 3, 30)]
    off = np.c_[rng.uniform(-3, 3, 10), rng.choice([-2.0, 2.0], 10), rng.uniform(-3, 3, 10)]
    X = np.vstack([plane, off])
    return geometry.project(K, R_a, t_a, X)[0], geometry.project(K, R_b, t_b, X)[0]


def test_planar_ratio_decides_for_a_plane_with_a_few_points_off_it():
    """30 points of a plane and 10 well off it: H explains 3/4 of the seeds F explains, so the
    pair is planar at a ratio of 0.7 and not at the default 0.8."""
    xa, xb = _plane_and_off_plane_pairs(np.random.default_rng(5))
    default = fit_pair(xa, xb)
    assert default is not None and not default.planar and default.inliers_f == 40 and default.inliers_h == 30
    lower = fit_pair(xa, xb, planar_ratio=0.7)
    assert lower is not None and lower.planar and lower.inliers == 30


def test_check_planar_ratio_takes_shares_in_zero_to_one():
    for ratio in (1e-3, 0.7, 1.0):
        check_planar_ratio(ratio)
    for ratio in (0.0, -0.5, 1.01, float("nan")):
        with pytest.raises(ValueError, match="EdgeConfig.planar_ratio must be in"):
            check_planar_ratio(ratio, "EdgeConfig.planar_ratio")


def test_too_few_seeds_give_no_model():
    rng = np.random.default_rng(2)
    xa = rng.uniform(0, 640, (MIN_SEEDS - 1, 2))
    assert fit_pair(xa, geometry.transfer(H_TRUE, xa)) is None
    assert fit_pair(np.zeros((0, 2)), np.zeros((0, 2))) is None


def test_residuals_are_symmetric_transfer_and_sampson_errors():
    rng = np.random.default_rng(3)
    xa, xb, F_true = _non_planar_pairs(rng, n=15)
    res_h, res_f = residuals(PairModel(H_TRUE, F_true), xa, xb)
    H_inv = np.linalg.inv(H_TRUE)
    for m, (a, b) in enumerate(zip(xa, xb)):
        forward = np.linalg.norm(geometry.transfer(H_TRUE, a[None])[0] - b)
        backward = np.linalg.norm(geometry.transfer(H_inv, b[None])[0] - a)
        assert res_h[m] == pytest.approx(0.5 * (forward + backward), rel=1e-12)
    np.testing.assert_allclose(res_f, geometry.sampson_distance(F_true, xa, xb), rtol=1e-9, atol=1e-12)
    assert res_f.max() < 1e-9  # true pairs under the true F
    off = xb + rng.normal(0, 3, xb.shape)
    np.testing.assert_allclose(residuals(PairModel(None, F_true), xa, off)[1],
                               geometry.sampson_distance(F_true, xa, off), rtol=1e-9)
    only_h, missing_f = residuals(PairModel(H_TRUE, None), xa, xb)
    assert np.all(np.isinf(missing_f)) and np.array_equal(only_h, res_h)
    missing_h, _ = residuals(PairModel(None, F_true), xa, xb)
    assert np.all(np.isinf(missing_h))
    singular_h, _ = residuals(PairModel(np.ones((3, 3)), None), xa, xb)
    assert np.all(np.isinf(singular_h))  # no pair agrees with a singular H
    no_h, no_f = residuals(None, xa, xb)  # a view pair without a model
    assert np.all(np.isinf(no_h)) and np.all(np.isinf(no_f))
    empty_h, empty_f = residuals(PairModel(H_TRUE, F_true), np.zeros((0, 2)), np.zeros((0, 2)))
    assert empty_h.shape == empty_f.shape == (0,)


def test_calibrated_cameras_give_an_essential_matrix_with_the_true_epipolar_geometry():
    rng = np.random.default_rng(4)
    xa, xb, F_true = _non_planar_pairs(rng)
    model = fit_pair(xa, xb, K_a=K, K_b=K)
    assert model is not None and model.essential and not model.planar
    _, res_f = residuals(model, xa, xb)
    assert res_f.max() < 1e-2
    F, G = model.F / np.linalg.norm(model.F), F_true / np.linalg.norm(F_true)
    np.testing.assert_allclose(F * np.sign(np.sum(F * G)), G, atol=1e-4)
    assert model.inliers_f == len(xa)  # every seed is in front of both cameras


def test_a_model_is_trusted_only_with_enough_inliers_making_enough_of_the_seeds():
    rng = np.random.default_rng(5)
    xa, xb, _ = _non_planar_pairs(rng, n=MIN_INLIERS + 5)
    model = fit_pair(xa, xb)
    assert model.trusted() and model.inliers == len(xa)
    # 35 true pairs among 65 random ones: fitted (5-point, calibrated), but explaining a
    # minority of its seeds
    xa, xb, _ = _non_planar_pairs(rng, n=35)
    drowned = fit_pair(np.r_[xa, rng.uniform(0, 640, (65, 2))], np.r_[xb, rng.uniform(0, 480, (65, 2))], K_a=K, K_b=K)
    assert drowned is not None and 35 <= drowned.inliers < 40 and not drowned.trusted()
    # random pairs only: a fundamental matrix always fits 7 of them, never trusted
    random_model = fit_pair(rng.uniform(0, 640, (40, 2)), rng.uniform(0, 480, (40, 2)))
    assert random_model is None or not random_model.trusted()
    assert PairModel(None, None, seeds=20, inliers_f=MIN_INLIERS - 1).trusted() is False
    assert PairModel(None, None, seeds=20, inliers_f=MIN_INLIERS).trusted() is True
    assert PairModel(None, None, planar=True, seeds=100, inliers_h=39).trusted() is False  # 39 % of seeds
    assert MIN_INLIER_RATIO == 0.4


def test_agrees_uses_the_selected_model_and_its_tolerance():
    rng = np.random.default_rng(6)
    xa, xb, F_true = _non_planar_pairs(rng, n=10)
    model = PairModel(H_TRUE, F_true, planar=False)
    off = xb + np.array([0.0, EPIPOLAR_PX * 3])  # off the epipolar line (not along it)
    assert model.agrees(xa, xb).all()
    _, res = residuals(model, xa, off)
    np.testing.assert_array_equal(model.agrees(xa, off), res <= EPIPOLAR_PX)
    assert not model.agrees(xa, off).all()
    planar = PairModel(H_TRUE, F_true, planar=True)
    ya = rng.uniform(0, 640, (10, 2))
    yb = geometry.transfer(H_TRUE, ya)
    assert planar.agrees(ya, yb).all()
    assert not planar.agrees(ya, yb + RANSAC_PX * 2).any()


def test_agreement_tolerance_follows_the_keypoint_noise():
    """3 sigma of the noise measured on the fit's inliers, within [AGREE_MIN_PX, EPIPOLAR_PX];
    the estimate itself, unclipped, is the model's noise_px."""
    rng = np.random.default_rng(7)
    xa, xb, _ = _non_planar_pairs(rng, n=80)
    exact = fit_pair(xa, xb, K_a=K, K_b=K)
    assert exact.epipolar_px == AGREE_MIN_PX and exact.noise_px < 0.1
    noisy = fit_pair(xa + rng.normal(0, 0.5, xa.shape), xb + rng.normal(0, 0.5, xb.shape), K_a=K, K_b=K)
    assert AGREE_MIN_PX < noisy.epipolar_px <= EPIPOLAR_PX
    assert noisy.noise_px == noisy.epipolar_px
    very_noisy = fit_pair(xa + rng.normal(0, 2.0, xa.shape), xb + rng.normal(0, 2.0, xb.shape), K_a=K, K_b=K)
    assert very_noisy.epipolar_px == EPIPOLAR_PX < very_noisy.noise_px


@pytest.mark.parametrize("calibrated", [False, True])
def test_fine_fit_is_kept_for_sub_pixel_keypoints_only(calibrated):
    """fine_px is tried first: kept (fit threshold and agreement tolerance FINE_PX) where the
    keypoints carry 0.1 px of noise, replaced by the fit at epipolar_px where they carry 1 px;
    without fine_px every model is fitted at epipolar_px."""
    rng = np.random.default_rng(8)
    xa, xb, _ = _non_planar_pairs(rng, n=120)
    intrinsics = {"K_a": K, "K_b": K} if calibrated else {}
    for noise, fit_px in ((0.1, FINE_PX), (1.0, EPIPOLAR_PX)):
        na, nb = xa + rng.normal(0, noise, xa.shape), xb + rng.normal(0, noise, xb.shape)
        model = fit_pair(na, nb, fine_px=FINE_PX, **intrinsics)
        assert model is not None and not model.planar and model.trusted()
        assert model.epipolar_fit_px == fit_px
        assert model.epipolar_px <= fit_px
        assert fit_pair(na, nb, **intrinsics).epipolar_fit_px == EPIPOLAR_PX
        assert fit_pair(na, nb, fine_px=EPIPOLAR_PX, **intrinsics).epipolar_fit_px == EPIPOLAR_PX


def test_a_fine_fit_explaining_less_than_half_of_the_seeds_is_not_kept(monkeypatch):
    """A generated scene with 1 px of keypoint noise (rome16k, 3 views, seed [11, 7]): at 0.5 px
    RANSAC bends view pair (0, 1)'s essential matrix onto 18 of its 39 seeds, which pass the
    sub-pixel share test. Explaining less than half of them, it is not kept: the pair is fitted at
    EPIPOLAR_PX, where far more of its true pairs agree (with the coarse trust ratio it was kept)."""
    problem = synthetic.random_scene_problem(synthetic.rome16k(3), np.random.default_rng([11, 7]))
    config = GCNSolver().edge_config
    view = problem.view_index
    pairs = np.array([(a, b) for a, b in true_pair_list(problem) if (view[a], view[b]) == (0, 1)])
    true_a, true_b = problem.keypoints[pairs[:, 0]], problem.keypoints[pairs[:, 1]]

    model = candidate_edges(problem, config).models[(0, 1)]
    assert model.epipolar_fit_px == EPIPOLAR_PX
    ratio = verify.FINE_MIN_INLIER_RATIO
    monkeypatch.setattr(verify, "FINE_MIN_INLIER_RATIO", MIN_INLIER_RATIO)
    bent = candidate_edges(problem, config).models[(0, 1)]
    assert bent.epipolar_fit_px == FINE_PX and bent.inliers_f < ratio * bent.seeds
    assert model.agrees(true_a, true_b).mean() > 0.9  # of its 80 true pairs: 96 %
    assert bent.agrees(true_a, true_b).mean() < 0.6  # 44 %


def test_fine_fit_sees_through_repetitions_a_coarse_fit_accepts():
    """Sub-pixel keypoints plus a third of pairs shifted 3 px across the (near-horizontal)
    epipolar lines, as repetitions a few pixels off the true lines: the 2 px fit tilts its
    lines towards them and accepts them, the fine fit keeps the true geometry and refuses them."""
    rng = np.random.default_rng(9)
    xa, xb, _ = _non_planar_pairs(rng, n=150)
    xa, xb = xa + rng.normal(0, 0.1, xa.shape), xb + rng.normal(0, 0.1, xb.shape)
    shifted = np.arange(150) < 50
    xb = xb + np.where(shifted[:, None], [0.0, 3.0], 0.0)
    fine = fit_pair(xa, xb, fine_px=FINE_PX)
    coarse = fit_pair(xa, xb)
    assert fine.epipolar_fit_px == FINE_PX
    assert fine.agrees(xa[shifted], xb[shifted]).mean() < 0.1
    assert fine.agrees(xa[~shifted], xb[~shifted]).mean() > 0.9
    assert coarse.agrees(xa[shifted], xb[shifted]).mean() > 0.5


def test_a_models_inverse_homography_is_computed_once_and_none_where_singular():
    H = np.array([[2.0, 0.0, 5.0], [0.0, 2.0, -3.0], [0.0, 0.0, 1.0]])
    model = PairModel(H=H, F=None, planar=True)
    assert model.H_inverse is model.H_inverse
    np.testing.assert_allclose(model.H_inverse @ H, np.eye(3), atol=1e-12)
    singular = PairModel(H=np.array([[1.0, 2.0, 0.0], [2.0, 4.0, 0.0], [0.0, 0.0, 0.0]]), F=None, planar=True)
    assert singular.H_inverse is None
    rh, rf = residuals(singular, np.zeros((3, 2)), np.ones((3, 2)))
    assert np.isinf(rh).all() and np.isinf(rf).all()  # no pair agrees with a singular H
    assert PairModel(H=None, F=np.eye(3)).H_inverse is None


def test_may_be_trusted_answers_as_the_full_fit_on_scenes_planes_and_seeds_without_geometry():
    """The cheap probe (H and F from pixels) says yes where fit_pair gives a trusted model,
    calibrated or not, and no for seed pairs of two views that share no scene."""
    rng = np.random.default_rng(6)
    xa, xb, _ = _non_planar_pairs(rng)
    plane_a, plane_b = _plane_and_off_plane_pairs(rng)
    for a, b in ((xa, xb), (plane_a, plane_b)):
        assert may_be_trusted(a, b)
        assert fit_pair(a, b).trusted() and fit_pair(a, b, K_a=K, K_b=K).trusted()
    for n in (20, 60, 200):
        a, b = rng.uniform(0, 640, (n, 2)), rng.uniform(0, 640, (n, 2))
        assert not may_be_trusted(a, b)
        model = fit_pair(a, b, K_a=K, K_b=K)
        assert model is None or not model.trusted()
    assert not may_be_trusted(xa[:MIN_SEEDS - 1], xb[:MIN_SEEDS - 1])
