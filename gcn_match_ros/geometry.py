"""Two-view and multi-view camera geometry, each formula once.

Conventions (``shared/spec/problem-format.md``): world→camera poses ``x ~ K (R X + t)``,
camera centre ``C = −Rᵀt``, OpenCV camera frame (x right, y down, z forward), pixels
(x, y). A fundamental matrix ``F_ab`` maps view a's points to lines in view b:
``x_bᵀ F_ab x_a = 0``. Poses on ROS topics (``geometry_msgs/PoseStamped``) are the
other way round, camera→world: :func:`rt_to_pose` and :func:`pose_to_rt` convert.

Everything is numpy float64 except :func:`skew`, :func:`essential_from_poses` and
:func:`epipolar_residuals`, which also take torch tensors (the training losses use them
with gradients).
"""
from __future__ import annotations

from typing import Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

__all__ = ["homogeneous", "skew", "camera_centers", "fundamental_from_poses", "essential_from_poses",
           "epipolar_residuals", "sampson_distance", "epipolar_distances", "epipolar_distance_matrix", "transfer", "project",
           "unproject", "unproject_sightings", "triangulate_pair", "triangulate_views", "triangulate_checked",
           "refine_points", "matrix_to_quat", "quat_to_matrix",
           "rt_to_pose", "pose_to_rt", "pose_msg_to_rt"]


def homogeneous(xy: np.ndarray) -> np.ndarray:
    """Append a 1 to every point. Shapes: (n, 2) -> (n, 3) float64."""
    xy = np.asarray(xy, dtype=np.float64)
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)


def skew(v):
    """Cross-product matrix [v]ₓ, so that ``skew(v) @ w == cross(v, w)``.

    Args:
        v: (*, 3) torch tensor (differentiable) or numpy array.

    Returns:
        (*, 3, 3) of the same kind.
    """
    if v.shape[-1] != 3:
        raise ValueError(f"skew: expected shape (*, 3), got {tuple(v.shape)}")
    if isinstance(v, Tensor):
        x, y, z = v.unbind(-1)
        o = torch.zeros_like(x)
        return torch.stack([torch.stack([o, -z, y], -1),
                            torch.stack([z, o, -x], -1),
                            torch.stack([-y, x, o], -1)], -2)
    x, y, z = np.moveaxis(np.asarray(v), -1, 0)
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


def camera_centers(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Camera centres ``C = −Rᵀt``. Shapes: R (V, 3, 3), t (V, 3) -> (V, 3)."""
    return -np.einsum("vji,vj->vi", R, t)


def fundamental_from_poses(K_a: np.ndarray, R_a: np.ndarray, t_a: np.ndarray,
                           K_b: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> np.ndarray:
    """F with ``x_bᵀ F x_a = 0`` (pixels) for world→camera poses of views a and b.

    ``F = K_b⁻ᵀ [t_ab]ₓ R_ab K_a⁻¹`` with the relative pose ``R_ab = R_b R_aᵀ``,
    ``t_ab = t_b − R_ab t_a``; not normalised (its scale is the baseline's).

    Shapes: K, R (3, 3), t (3,) each -> (3, 3) float64.
    """
    R_ab = R_b @ R_a.T
    t_ab = t_b - R_ab @ t_a
    return np.linalg.inv(K_b).T @ skew(t_ab) @ R_ab @ np.linalg.inv(K_a)


def _check_pose(R: Tensor, t: Tensor, name: str) -> None:
    if R.dim() < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R_{name}: expected shape (*, 3, 3), got {tuple(R.shape)}")
    if t.dim() < 1 or t.shape[-1] != 3:
        raise ValueError(f"t_{name}: expected shape (*, 3), got {tuple(t.shape)}")


def essential_from_poses(R_i: Tensor, t_i: Tensor, R_j: Tensor, t_j: Tensor, eps: float = 1e-12) -> Tensor:
    r"""Essential matrix between views i and j for world→camera poses, unit baseline.

    With ``x ~ K (R X + t)`` the camera centre is C = −Rᵀt and a calibrated point x
    has world direction Rᵀx. Two rays meet iff they are coplanar with the baseline:

    .. math::
        (R_i^\top x_i) \cdot \big(\hat b \times R_j^\top x_j\big) = x_i^\top
        \underbrace{R_i [\hat b]_\times R_j^\top}_{E_{ij}} x_j = 0,
        \qquad \hat b = \frac{C_j - C_i}{\lVert C_j - C_i\rVert}

    The baseline is normalised (max(‖b‖, eps)) so residuals do not depend on the
    scene's scale; coincident centres give E ≈ 0.

    Shapes: R_i, R_j (*, 3, 3), t_i, t_j (*, 3) broadcastable -> (*, 3, 3).
    """
    _check_pose(R_i, t_i, "i")
    _check_pose(R_j, t_j, "j")
    C_i = -(R_i.transpose(-1, -2) @ t_i.unsqueeze(-1)).squeeze(-1)
    C_j = -(R_j.transpose(-1, -2) @ t_j.unsqueeze(-1)).squeeze(-1)
    b = C_j - C_i
    b = b / b.norm(dim=-1, keepdim=True).clamp(min=eps)
    return R_i @ skew(b) @ R_j.transpose(-1, -2)


def epipolar_residuals(X_i: Tensor, X_j: Tensor, R_i: Tensor, t_i: Tensor, R_j: Tensor, t_j: Tensor,
                       normalize_rays: bool = False) -> Tensor:
    r"""Epipolar residuals |x_iᵀ E_ij x_j| of point pairs (see :func:`essential_from_poses`).

    Poses are world→camera (``x ~ K (R X + t)``), points calibrated homogeneous
    (K⁻¹[u, v, 1], :func:`node_features.calibrated_points`). The baseline is unit length,
    so the residual is scale-free; with ``normalize_rays`` the points are also made
    unit vectors, which bounds the residual by 1 (the volume spanned by the two rays
    and the baseline direction).

    Broadcasting follows ``torch.matmul``: points (*, N, 3) pair row by row, the pose
    batch (*) broadcasts with the points' leading dimensions. Examples:
    (N, 3) with single poses (3, 3)/(3,) -> (N,); (B, N, 3) with (B, 3, 3)/(B, 3) -> (B, N);
    all pairs of two sets: X_i (n, 1, 3), X_j (1, m, 3), single poses -> (n, m).

    Shapes:
        X_i, X_j (*, N, 3); R_i, R_j (*, 3, 3); t_i, t_j (*, 3) -> (*, N).
    """
    if X_i.dim() < 2 or X_i.shape[-1] != 3:
        raise ValueError(f"X_i: expected shape (*, N, 3), got {tuple(X_i.shape)}")
    if X_j.dim() < 2 or X_j.shape[-1] != 3:
        raise ValueError(f"X_j: expected shape (*, N, 3), got {tuple(X_j.shape)}")
    Ess = essential_from_poses(R_i, t_i, R_j, t_j)
    if normalize_rays:
        X_i = X_i / X_i.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        X_j = X_j / X_j.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    return ((X_i @ Ess) * X_j).sum(dim=-1).abs()


def sampson_distance(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distance of pairs xa[m] <-> xb[m] under F (``x_bᵀ F x_a = 0``), pixels.

    Shapes: F (3, 3), xa, xb (M, 2) -> (M,) float64.
    """
    ha, hb = homogeneous(xa), homogeneous(xb)
    Fa = ha @ F.T   # lines in b
    Ftb = hb @ F    # lines in a
    num = np.abs((hb * Fa).sum(1))
    den = np.sqrt(Fa[:, 0] ** 2 + Fa[:, 1] ** 2 + Ftb[:, 0] ** 2 + Ftb[:, 1] ** 2)
    return num / np.maximum(den, 1e-12)


def epipolar_distances(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """For pairs xa[m] <-> xb[m], the larger of the two point-to-epipolar-line distances (each
    in its own image's pixels), under F with ``x_bᵀ F x_a = 0``: the diagonal of
    :func:`epipolar_distance_matrix` (up to rounding: a row sum, not a matrix product).

    Shapes: F (3, 3), xa, xb (M, 2) -> (M,) float64.
    """
    ha, hb = homogeneous(xa), homogeneous(xb)
    la = ha @ F.T  # lines in b
    lb = hb @ F    # lines in a
    d_b = np.abs((la * hb).sum(1)) / np.maximum(np.linalg.norm(la[:, :2], axis=1), 1e-12)
    d_a = np.abs((ha * lb).sum(1)) / np.maximum(np.linalg.norm(lb[:, :2], axis=1), 1e-12)
    return np.maximum(d_a, d_b)


def epipolar_distance_matrix(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """For every pair of xa and xb, the larger of the two point-to-epipolar-line distances
    (each in its own image's pixels), under F with ``x_bᵀ F x_a = 0``.

    Shapes: F (3, 3), xa (na, 2), xb (nb, 2) -> (na, nb) float64.
    """
    ha, hb = homogeneous(xa), homogeneous(xb)
    la = ha @ F.T  # (na, 3) lines in b
    lb = hb @ F    # (nb, 3) lines in a
    d_b = np.abs(la @ hb.T) / np.maximum(np.linalg.norm(la[:, :2], axis=1), 1e-12)[:, None]
    d_a = np.abs(ha @ lb.T) / np.maximum(np.linalg.norm(lb[:, :2], axis=1), 1e-12)[None, :]
    return np.maximum(d_a, d_b)


def transfer(H: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Points mapped by a homography. Shapes: H (3, 3), x (n, 2) -> (n, 2) float64."""
    h = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1) @ H.T
    z = h[:, 2:3]
    return h[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)


def project(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Pixels and depths of world points in one camera (no visibility test: points behind
    the camera get a pixel too, and inf/NaN at depth 0).

    Shapes: K, R (3, 3), t (3,), X (*, 3) -> uv (*, 2), depth (*,).
    """
    cam = X @ R.T + t
    uvw = cam @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[..., :2] / uvw[..., 2:3]
    return uv, cam[..., 2]


def unproject(K: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Calibrated homogeneous points K⁻¹ [x, y, 1], scaled so the last coordinate is 1 (it
    already is for the usual upper-triangular K).

    Shapes: K (3, 3), xy (n, 2) -> (n, 3) float64.
    """
    X = np.linalg.solve(K, homogeneous(xy).T).T
    z = X[:, 2:3]
    return X / np.where(np.abs(z) > 1e-12, z, 1.0)


def triangulate_pair(P_a: np.ndarray, P_b: np.ndarray, u_a: np.ndarray, u_b: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of paired calibrated points seen by two cameras.

    Args:
        P_a, P_b: (3, 4) ``[R | t]`` of the two cameras.
        u_a, u_b: (m, 2) the first two entries of K⁻¹ [x, y, 1] of each pair.

    Returns:
        (m, 3) world points (NaN/inf for points at infinity).
    """
    rows = [u_a[:, :1] * P_a[2] - P_a[0], u_a[:, 1:] * P_a[2] - P_a[1],
            u_b[:, :1] * P_b[2] - P_b[0], u_b[:, 1:] * P_b[2] - P_b[1]]
    X = np.linalg.svd(np.stack(rows, axis=1))[2][:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:]


def triangulate_views(P: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of points seen in m >= 2 views each, a batch at a time.

    Args:
        P: (B, m, 3, 4) ``[R | t]`` of each member's camera.
        u: (B, m, 2) the first two entries of K⁻¹ [x, y, 1] of each member.

    Returns:
        (B, 3) world points (NaN/inf for points at infinity).
    """
    rows = np.concatenate([u[..., :1] * P[..., 2, :] - P[..., 0, :],
                           u[..., 1:] * P[..., 2, :] - P[..., 1, :]], axis=1)  # (B, 2m, 4)
    X = np.linalg.svd(rows)[2][..., -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:]


def unproject_sightings(K: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """:func:`unproject` of sightings that each have their own intrinsics, a batch at a time.

    Shapes: K (B, m, 3, 3), xy (B, m, 2) -> (B, m, 3) float64, last coordinate 1.
    """
    u = np.einsum("bmij,bmj->bmi", np.linalg.inv(K), np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], -1))
    return u / u[..., 2:]


def triangulate_checked(K: np.ndarray, R: np.ndarray, t: np.ndarray, xy: np.ndarray, refine: int = 0
                        ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate points from all their sightings at once (:func:`triangulate_views`) and
    say how well each explains them, a batch at a time.

    Args:
        K, R, t: (B, m, 3, 3), (B, m, 3, 3), (B, m, 3) intrinsics and world→camera poses of
            each sighting's camera; xy: (B, m, 2) the sightings, pixels.
        refine: Gauss-Newton steps on the sum of squared reprojection errors from the linear
            point (:func:`refine_points`); 0: the linear point, which minimises an algebraic
            error and weighs the sightings by their depth.

    Returns:
        X (B, 3) world points; err (B,) the largest reprojection error over the sightings
        (inf where not finite); in_front (B,) X is finite and in front of every camera.
    """
    u = unproject_sightings(K, xy)[..., :2]
    X = triangulate_views(np.concatenate([R, t[..., None]], axis=-1), u)
    if refine:
        X = refine_points(K, R, t, xy, X, refine)
    cam = np.einsum("bmij,bj->bmi", R, X) + t                               # (B, m, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        px = np.einsum("bmij,bmj->bmi", K, cam)
        px = px[..., :2] / px[..., 2:]
    err = np.linalg.norm(px - xy, axis=-1)
    err = np.where(np.isfinite(err), err, np.inf).max(axis=1)
    in_front = (cam[..., 2] > 0).all(axis=1) & np.isfinite(X).all(axis=1)
    return X, err, in_front


def refine_points(K: np.ndarray, R: np.ndarray, t: np.ndarray, xy: np.ndarray, X: np.ndarray,
                  steps: int = 3) -> np.ndarray:
    """World points moved by Gauss-Newton steps to lower the sum of their squared reprojection
    errors, pixels (the maximum-likelihood point for Gaussian pixel noise). A point whose step
    is not finite, or would not lower its error, keeps its place.

    Args: as :func:`triangulate_checked`; X (B, 3) the starting points.

    Returns:
        (B, 3) the refined points.
    """
    X = np.array(X, np.float64)
    KR = K @ R                                                              # (B, m, 3, 3)
    Kt = np.einsum("bmij,bmj->bmi", K, t)                                   # (B, m, 3)

    def residuals(points):
        p = np.einsum("bmij,bj->bmi", KR, points) + Kt                     # (B, m, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            return p, p[..., :2] / p[..., 2:] - xy

    p, r = residuals(X)
    cost = np.sum(r * r, axis=(1, 2))
    for _ in range(steps):
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = 1.0 / p[..., 2]
            # d(projection)/dp (B, m, 2, 3), then by the chain rule d/dX = that @ K R
            d_proj = np.zeros(p.shape[:2] + (2, 3))
            d_proj[..., 0, 0] = d_proj[..., 1, 1] = inv_z
            d_proj[..., 0, 2] = -p[..., 0] * inv_z ** 2
            d_proj[..., 1, 2] = -p[..., 1] * inv_z ** 2
            J = d_proj @ KR                                                 # (B, m, 2, 3)
            H = np.einsum("bmki,bmkj->bij", J, J)
            g = np.einsum("bmki,bmk->bi", J, r)
            ok = np.isfinite(H).all(axis=(1, 2)) & np.isfinite(g).all(axis=1) & (np.abs(np.linalg.det(H)) > 1e-12)
        if not ok.any():
            break
        step = np.zeros_like(X)
        step[ok] = -np.linalg.solve(H[ok], g[ok][..., None])[..., 0]
        p_new, r_new = residuals(X + step)
        new_cost = np.sum(r_new * r_new, axis=(1, 2))
        better = ok & np.isfinite(new_cost) & (new_cost < cost)
        if not better.any():
            break
        X[better], cost[better] = X[better] + step[better], new_cost[better]
        p[better], r[better] = p_new[better], r_new[better]
    return X


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (x, y, z, w) with w >= 0."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Quaternion (x, y, z, w) (normalised here) -> rotation matrix (3, 3).

    Raises:
        ValueError: a quaternion that is not finite or of norm ~0 (no rotation: e.g. a driver's
            all-zero "orientation unknown").
    """
    q = np.asarray(q, dtype=np.float64)
    norm = float(np.linalg.norm(q)) if np.all(np.isfinite(q)) else float("nan")
    if not norm > 1e-9:
        raise ValueError(f"orientation {q.tolist()} is not a rotation (a finite quaternion of norm > 0)")
    x, y, z, w = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rt_to_pose(R: np.ndarray, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """World→camera (R, t) -> the camera's pose in the world, as ``PoseStamped`` holds it:
    (position C = −Rᵀt (3,), orientation of R_wc = Rᵀ as quaternion x, y, z, w (4,))."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return -R.T @ t, matrix_to_quat(R.T)


def pose_to_rt(position: Sequence[float], quat_xyzw: Sequence[float]) -> Tuple[np.ndarray, np.ndarray]:
    """A camera's pose in the world (position C, orientation R_wc) -> world→camera
    ``R = R_wcᵀ``, ``t = −R C``.

    Raises:
        ValueError: a position that is not finite, or an orientation that is no rotation
            (:func:`quat_to_matrix`).
    """
    C = np.asarray(position, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(C)):
        raise ValueError(f"position {C.tolist()} is not finite")
    R = quat_to_matrix(quat_xyzw).T
    return R, -R @ C


def pose_msg_to_rt(pose) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`pose_to_rt` of a ``geometry_msgs/Pose``: rclpy's message or a bag reader's (anything
    with ``position.x/y/z`` and ``orientation.x/y/z/w``; the core imports no ROS).

    Raises:
        ValueError: as :func:`pose_to_rt` (a position that is not finite, no rotation).
    """
    p, q = pose.position, pose.orientation
    return pose_to_rt([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
