"""Tests of gcn_match_ros.geometry: every formula against a closed-form or brute-force reference."""
import numpy as np
import pytest
import torch

from gcn_match_ros import geometry
from gcn_match_ros.geometry import epipolar_residuals, essential_from_poses, skew

from conftest import calibrated_scene as _scene, look_at, random_rotation as _rotation

D64 = torch.float64


def test_pose_convention_round_trip():
    rng = np.random.default_rng(2)
    for _ in range(50):
        R, t = _rotation(rng), rng.normal(size=3) * 5
        C, q = geometry.rt_to_pose(R, t)
        np.testing.assert_allclose(R @ C + t, 0, atol=1e-12)  # position is the camera centre
        R_wc = geometry.quat_to_matrix(q)
        np.testing.assert_allclose(R_wc, R.T, atol=1e-12)  # orientation is camera->world
        np.testing.assert_allclose(R_wc @ [0, 0, 1], R[2], atol=1e-12)  # optical axis in world
        R2, t2 = geometry.pose_to_rt(C, q)
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(t2, t, atol=1e-12)
    for R in (np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        np.testing.assert_allclose(geometry.quat_to_matrix(geometry.matrix_to_quat(R)), R, atol=1e-12)


def test_a_pose_that_is_none_is_refused():
    # a quaternion a little off unit length is normalised, as ROS messages' often are
    np.testing.assert_allclose(geometry.quat_to_matrix([0.0, 0.0, 0.0, 1.001]), np.eye(3), atol=1e-12)
    for q in ([0.0, 0.0, 0.0, 0.0], [np.nan, 0.0, 0.0, 1.0], [0.0, np.inf, 0.0, 1.0]):
        with pytest.raises(ValueError, match="is not a rotation"):
            geometry.pose_to_rt([1.0, 2.0, 3.0], q)
    with pytest.raises(ValueError, match=r"position \[1.0, nan, 3.0\] is not finite"):
        geometry.pose_to_rt([1.0, np.nan, 3.0], [0.0, 0.0, 0.0, 1.0])


def test_a_pose_message_is_read_as_its_fields():
    from types import SimpleNamespace as NS

    C, q = [1.0, 2.0, 3.0], geometry.matrix_to_quat(geometry.quat_to_matrix([0.1, -0.2, 0.3, 0.9]))
    pose = NS(position=NS(x=C[0], y=C[1], z=C[2]), orientation=NS(x=q[0], y=q[1], z=q[2], w=q[3]))
    for got, want in zip(geometry.pose_msg_to_rt(pose), geometry.pose_to_rt(C, q)):
        np.testing.assert_array_equal(got, want)
    pose.orientation = NS(x=0.0, y=0.0, z=0.0, w=0.0)  # a driver's "orientation unknown"
    with pytest.raises(ValueError, match="is not a rotation"):
        geometry.pose_msg_to_rt(pose)


def test_skew_is_cross_product():
    v, w = torch.randn(5, 3, dtype=D64), torch.randn(5, 3, dtype=D64)
    assert torch.allclose(skew(v) @ w[..., None], torch.linalg.cross(v, w)[..., None])


def test_epipolar_residuals_broadcast_shapes_and_block_form():
    rng = np.random.default_rng(1)
    prob, X = _scene(rng, n_views=2, p=7)
    X = torch.from_numpy(X)
    R, t = torch.from_numpy(prob.R), torch.from_numpy(prob.t)
    Xa, Xb = X[:7], X[7:]
    # row by row
    r = epipolar_residuals(Xa, Xb, R[0], t[0], R[1], t[1])
    assert r.shape == (7,)
    # all pairs: (n, 1, 3) x (1, m, 3) -> (n, m), equals the matrix form
    allp = epipolar_residuals(Xa[:, None], Xb[None], R[0], t[0], R[1], t[1])
    assert allp.shape == (7, 7)
    assert torch.allclose(allp, (Xa @ essential_from_poses(R[0], t[0], R[1], t[1]) @ Xb.T).abs())
    assert torch.allclose(torch.diagonal(allp), r)
    # true pairs (same track) are ~0
    ta, tb = prob.gt_track[:7], prob.gt_track[7:]
    match = torch.from_numpy(ta[:, None] == tb[None, :])
    assert allp[match].max() < 1e-12 and allp[~match].min() > 0
    # batch of poses: (B, N, 3) with (B, 3, 3) / (B, 3) -> (B, N)
    B = 4
    Rb, tb_ = R[0].expand(B, 3, 3), t[0].expand(B, 3)
    Rc, tc = R[1].expand(B, 3, 3), t[1].expand(B, 3)
    rb = epipolar_residuals(Xa.expand(B, 7, 3), Xb.expand(B, 7, 3), Rb, tb_, Rc, tc)
    assert rb.shape == (B, 7) and torch.allclose(rb, r.expand(B, 7))
    # normalised rays bound the residual by 1
    rn = epipolar_residuals(Xa[:, None], Xb[None], R[0], t[0], R[1], t[1], normalize_rays=True)
    assert rn.shape == (7, 7) and rn.max() <= 1.0


# --------------------------------------------------------------------------------------
# Two-view geometry against closed forms and brute force
# --------------------------------------------------------------------------------------
def _two_posed_cameras(rng):
    """Two cameras with different intrinsics ~10 m from the origin, 25 deg apart, looking at
    it, and 30 world points near the origin (in front of both)."""
    K_a = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    K_b = np.array([[620.0, 0, 300], [0, 615, 250], [0, 0, 1]])
    R_a, t_a = look_at(np.array([0.0, -10.0, 0.5]), np.zeros(3))
    angle = np.radians(25)
    R_b, t_b = look_at(np.array([10 * np.sin(angle), -10 * np.cos(angle), 1.5]), np.zeros(3))
    X = rng.uniform(-2, 2, (30, 3))
    return (K_a, R_a, t_a), (K_b, R_b, t_b), X


def _fundamental_hartley_zisserman(cam_a, cam_b):
    """F = [e_b]x P_b P_a^+ (Hartley & Zisserman, eq. 9.1): an independent construction."""
    (K_a, R_a, t_a), (K_b, R_b, t_b) = cam_a, cam_b
    P_a, P_b = K_a @ np.c_[R_a, t_a], K_b @ np.c_[R_b, t_b]
    e_b = P_b @ np.r_[-R_a.T @ t_a, 1.0]
    return geometry.skew(e_b) @ P_b @ np.linalg.pinv(P_a)


def _unit(F):
    """F scaled to unit Frobenius norm with a positive largest entry (F is defined up to scale)."""
    F = F / np.linalg.norm(F)
    return F * np.sign(F.flat[np.argmax(np.abs(F))])


def test_fundamental_from_poses_holds_for_projected_points_and_has_rank_two():
    rng = np.random.default_rng(0)
    cam_a, cam_b, X = _two_posed_cameras(rng)
    xa, depth_a = geometry.project(*cam_a, X)
    xb, depth_b = geometry.project(*cam_b, X)
    assert np.all(depth_a > 0) and np.all(depth_b > 0)
    F = geometry.fundamental_from_poses(*cam_a, *cam_b)
    Fn = F / np.linalg.norm(F)
    # x_b^T F x_a = 0 for every projected point (homogeneous pixels are ~1e3: relative to that)
    algebraic = np.einsum("ni,ij,nj->n", geometry.homogeneous(xb), Fn, geometry.homogeneous(xa))
    assert np.abs(algebraic).max() < 1e-12 * 1e3 ** 2
    # and not for wrong pairs: the check is not vacuous
    assert np.median(np.abs(np.einsum("ni,ij,nj->n", geometry.homogeneous(xb[::-1]), Fn,
                                      geometry.homogeneous(xa)))) > 1e-3
    s = np.linalg.svd(F, compute_uv=False)
    assert s[2] < 1e-12 * s[0] and s[1] > 1e-3 * s[0]  # rank exactly 2
    # the epipoles: images of the other camera's centre, null vectors of F and F^T
    C = geometry.camera_centers(np.stack([cam_a[1], cam_b[1]]), np.stack([cam_a[2], cam_b[2]]))
    e_a = geometry.homogeneous(geometry.project(*cam_a, C[1])[0][None])[0]
    e_b = geometry.homogeneous(geometry.project(*cam_b, C[0])[0][None])[0]
    np.testing.assert_allclose(Fn @ e_a / np.linalg.norm(e_a), 0, atol=1e-12)
    np.testing.assert_allclose(e_b @ Fn / np.linalg.norm(e_b), 0, atol=1e-12)
    np.testing.assert_allclose(_unit(F), _unit(_fundamental_hartley_zisserman(cam_a, cam_b)), atol=1e-10)


def test_sampson_distance_is_zero_for_true_pairs_and_equals_the_formula():
    rng = np.random.default_rng(1)
    cam_a, cam_b, X = _two_posed_cameras(rng)
    xa, xb = geometry.project(*cam_a, X)[0], geometry.project(*cam_b, X)[0]
    F = geometry.fundamental_from_poses(*cam_a, *cam_b)
    assert geometry.sampson_distance(F, xa, xb).max() < 1e-9
    # any pairs: the first-order geometric error, written out pair by pair
    ya, yb = rng.uniform(0, 640, (20, 2)), rng.uniform(0, 480, (20, 2))
    expected = []
    for a, b in zip(ya, yb):
        ha, hb = np.r_[a, 1.0], np.r_[b, 1.0]
        Fa, Ftb = F @ ha, F.T @ hb
        expected.append(abs(hb @ F @ ha) / np.sqrt(Fa[0] ** 2 + Fa[1] ** 2 + Ftb[0] ** 2 + Ftb[1] ** 2))
    np.testing.assert_allclose(geometry.sampson_distance(F, ya, yb), expected, rtol=1e-12)
    # scale-free in F
    np.testing.assert_allclose(geometry.sampson_distance(1e-6 * F, ya, yb), expected, rtol=1e-9)


def test_epipolar_distance_matrix_is_the_larger_point_to_line_distance():
    rng = np.random.default_rng(2)
    F = rng.normal(size=(3, 3))
    xa, xb = rng.uniform(0, 640, (7, 2)), rng.uniform(0, 480, (5, 2))
    M = geometry.epipolar_distance_matrix(F, xa, xb)
    assert M.shape == (7, 5)
    for i, a in enumerate(xa):
        for j, b in enumerate(xb):
            ha, hb = np.r_[a, 1.0], np.r_[b, 1.0]
            line_b, line_a = F @ ha, F.T @ hb  # the epipolar lines of a in b, and of b in a
            to_b = abs(line_b @ hb) / np.hypot(line_b[0], line_b[1])
            to_a = abs(line_a @ ha) / np.hypot(line_a[0], line_a[1])
            assert M[i, j] == pytest.approx(max(to_a, to_b), rel=1e-12)


def test_epipolar_distances_are_the_diagonal_of_the_matrix():
    rng = np.random.default_rng(3)
    F = rng.normal(size=(3, 3))
    xa, xb = rng.uniform(0, 640, (50, 2)), rng.uniform(0, 480, (50, 2))
    d = geometry.epipolar_distances(F, xa, xb)
    # equal to a few ulps, not bitwise: the row-wise products are summed in another order than
    # the matrix product's
    np.testing.assert_allclose(d, np.diag(geometry.epipolar_distance_matrix(F, xa, xb)), rtol=1e-13, atol=0)


def test_triangulate_pair_recovers_the_points():
    rng = np.random.default_rng(4)
    (K_a, R_a, t_a), (K_b, R_b, t_b), X = _two_posed_cameras(rng)
    u_a = geometry.unproject(K_a, geometry.project(K_a, R_a, t_a, X)[0])[:, :2]
    u_b = geometry.unproject(K_b, geometry.project(K_b, R_b, t_b, X)[0])[:, :2]
    got = geometry.triangulate_pair(np.c_[R_a, t_a], np.c_[R_b, t_b], u_a, u_b)
    np.testing.assert_allclose(got, X, atol=1e-9)


def test_project_and_unproject_are_inverse():
    rng = np.random.default_rng(5)
    K = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    R, t = _rotation(rng), np.array([0.2, -0.1, 6.0])
    X = rng.uniform(-1, 1, (4, 5, 3))
    uv, depth = geometry.project(K, R, t, X)
    assert uv.shape == (4, 5, 2) and depth.shape == (4, 5)
    cam = X @ R.T + t
    np.testing.assert_allclose(depth, cam[..., 2], rtol=1e-15)
    rays = geometry.unproject(K, uv.reshape(-1, 2))
    np.testing.assert_allclose(rays[:, 2], 1.0, rtol=0, atol=0)
    np.testing.assert_allclose(rays * depth.reshape(-1, 1), cam.reshape(-1, 3), atol=1e-12)
    # a camera centre is at depth 0 in its own camera
    C = geometry.camera_centers(R[None], t[None])[0]
    np.testing.assert_allclose(R @ C + t, 0, atol=1e-12)
    np.testing.assert_array_equal(geometry.homogeneous(np.array([[2.0, 3.0]])), [[2.0, 3.0, 1.0]])


def test_transfer_by_a_homography_and_its_inverse():
    rng = np.random.default_rng(6)
    x = rng.uniform(0, 640, (25, 2))
    affine = np.array([[2.0, 0, 1], [0, 3, -2], [0, 0, 1]])
    np.testing.assert_allclose(geometry.transfer(affine, x), np.c_[2 * x[:, 0] + 1, 3 * x[:, 1] - 2], rtol=1e-15)
    H = np.array([[1.1, 0.05, 12.0], [-0.03, 0.95, -7.0], [2e-4, -1e-4, 1.0]])
    y = geometry.transfer(H, x)
    expected = [(H @ np.r_[p, 1.0])[:2] / (H @ np.r_[p, 1.0])[2] for p in x]
    np.testing.assert_allclose(y, expected, rtol=1e-13)
    np.testing.assert_allclose(geometry.transfer(np.linalg.inv(H), y), x, atol=1e-9)


def test_skew_numpy_and_torch_agree_and_are_antisymmetric():
    rng = np.random.default_rng(7)
    v, w = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    S = skew(v)
    assert isinstance(S, np.ndarray) and S.shape == (5, 3, 3)
    np.testing.assert_allclose((S @ w[..., None])[..., 0], np.cross(v, w), rtol=1e-14, atol=1e-15)
    np.testing.assert_array_equal(S, -np.swapaxes(S, -1, -2))
    St = skew(torch.from_numpy(v))
    assert isinstance(St, torch.Tensor) and St.dtype == D64
    np.testing.assert_array_equal(St.numpy(), S)
    with pytest.raises(ValueError, match=r"skew: expected shape \(\*, 3\), got \(2, 4\)"):
        skew(np.zeros((2, 4)))


def _sightings(rng, b=50, m=4):
    """Points 2-20 m in front of m cameras spread over 2 m, each turned a little."""
    K = np.tile(np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]), (b, m, 1, 1))
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(rng.normal(0, 0.05, (b * m, 3))).as_matrix().reshape(b, m, 3, 3)
    centers = rng.uniform(-1, 1, (b, m, 3))
    t = -np.einsum("bmij,bmj->bmi", R, centers)
    X = np.c_[rng.uniform(-2, 2, (b, 2)), rng.uniform(2, 20, b)]
    cam = np.einsum("bmij,bj->bmi", R, X) + t
    px = np.einsum("bmij,bmj->bmi", K, cam)
    return K, R, t, X, px[..., :2] / px[..., 2:]


def _squared_errors(K, R, t, X, xy):
    p = np.einsum("bmij,bmj->bmi", K, np.einsum("bmij,bj->bmi", R, X) + t)
    return ((p[..., :2] / p[..., 2:] - xy) ** 2).sum(axis=(1, 2))


def test_refined_points_keep_exact_sightings_and_lower_noisy_ones_errors():
    rng = np.random.default_rng(3)
    K, R, t, X, xy = _sightings(rng)
    exact, err, in_front = geometry.triangulate_checked(K, R, t, xy, refine=3)
    np.testing.assert_allclose(exact, X, atol=1e-6)
    assert in_front.all() and err.max() < 1e-6
    noisy = xy + rng.normal(0, 1.5, xy.shape)
    linear, _, _ = geometry.triangulate_checked(K, R, t, noisy)
    refined, _, _ = geometry.triangulate_checked(K, R, t, noisy, refine=3)
    before, after = _squared_errors(K, R, t, linear, noisy), _squared_errors(K, R, t, refined, noisy)
    assert (after <= before + 1e-9).all() and after.sum() < before.sum()
    # a start far off converges to the same point
    again = geometry.refine_points(K, R, t, noisy, refined + rng.normal(0, 0.05, refined.shape), steps=10)
    np.testing.assert_allclose(again, refined, atol=1e-4)
