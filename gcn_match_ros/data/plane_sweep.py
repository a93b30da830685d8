"""Depth of single keypoints by plane sweep: the photo-consistency evidence behind
:func:`.labels.label_photometric`.

A keypoint x of view v is lifted to a 3D point by sweeping depth along its ray (a coarse
grid, then a fine one around the coarse peak): at each depth z, on a grid uniform in 1/z,
the (2·half+1)² patch around x, taken as a plane at depth z facing camera v, is projected
into the support views and compared with them by normalised cross-correlation (NCC). The
depth whose mean NCC over the support views is highest wins when

- that mean is at least ``min_ncc`` (the patch really looks alike), and
- it beats the best depth more than ``exclusion_px`` of disparity away by ``margin`` (one
  clear peak: repeated structure along the epipolar line gives several and is refused).

Flat patches (standard deviation under ``min_std`` grey levels) and patches leaving an
image do not count. Poses are world→camera, ``x ~ K (R X + t)`` (:class:`.scenes.Scene`).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence, Tuple

import cv2
import numpy as np

from ..geometry import camera_centers, project

__all__ = ["SweepConfig", "lift", "patch_ncc", "project_in_front", "inverse_depths"]

_REMAP_ROWS = 30000  # cv2.remap maps must stay below SHRT_MAX rows
_DEPTH_BLOCK = 16


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """Plane-sweep settings (module docstring)."""

    half: int = 5
    coarse_px: float = 1.5  # disparity between coarse grid depths in the widest support view
    step_px: float = 0.25  # the same for the fine grid around the coarse peak
    max_steps: int = 400
    min_ncc: float = 0.8
    margin: float = 0.1
    exclusion_px: float = 2.0
    min_std: float = 2.0


def project_in_front(K: np.ndarray, R: np.ndarray, t: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels of world points ``X`` (*, 3) in camera (K, R, t) -> (*, 2); NaN behind it."""
    px, depth = project(K, R, t, X)
    return np.where(depth[..., None] > 0, px, np.nan)


def _sample(image: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Bilinear grey values of ``image`` at pixels ``at`` (*, 2); NaN outside or at NaN."""
    flat = np.nan_to_num(at, nan=-1e4).astype(np.float32).reshape(-1, 1, 2)
    out = np.empty(flat.shape[0], np.float32)
    for s in range(0, flat.shape[0], _REMAP_ROWS):
        m = flat[s:s + _REMAP_ROWS]
        out[s:s + _REMAP_ROWS] = cv2.remap(image, m[..., 0], m[..., 1], cv2.INTER_LINEAR,
                                           borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan).ravel()
    return out.reshape(at.shape[:-1])


def _ncc(a: np.ndarray, b: np.ndarray, min_std: float) -> np.ndarray:
    """NCC over the last axis (patch pixels); NaN for flat patches or NaN samples."""
    a = a - a.mean(axis=-1, keepdims=True)
    b = b - b.mean(axis=-1, keepdims=True)
    sa, sb = np.sqrt((a * a).mean(axis=-1)), np.sqrt((b * b).mean(axis=-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        ncc = (a * b).mean(axis=-1) / (sa * sb)
    return np.where((sa >= min_std) & (sb >= min_std), ncc, np.nan)


def _offsets(half: int) -> np.ndarray:
    o = np.arange(-half, half + 1, dtype=np.float64)
    return np.stack(np.meshgrid(o, o), axis=-1).reshape(-1, 2)


def _patch_points(K: np.ndarray, R: np.ndarray, t: np.ndarray, xy: np.ndarray, depth: np.ndarray,
                  half: int) -> np.ndarray:
    """World points of the patches around pixels xy (n, 2) on fronto-parallel planes at depths
    ``depth`` (n, d) of that camera -> (n, d, P, 3)."""
    pix = xy[:, None, :] + _offsets(half)[None]
    rays = np.concatenate([pix, np.ones(pix.shape[:2] + (1,))], axis=-1) @ np.linalg.inv(K).T  # z = 1
    cam = rays[:, None] * depth[:, :, None, None]
    return (cam - t) @ R  # R^T (x - t)


def patch_ncc(images: Sequence[np.ndarray], K: np.ndarray, R: np.ndarray, t: np.ndarray, v: int,
              xy: np.ndarray, depth: np.ndarray, u: int, config: SweepConfig = SweepConfig()) -> np.ndarray:
    """NCC between the patches of view v around ``xy`` (n, 2), as planes at ``depth`` (n, d)
    facing camera v, and what view u sees there -> (n, d)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    own = _sample(images[v], xy[:, None, :] + _offsets(config.half)[None])[:, None, :]
    out = np.empty(depth.shape)
    for d0 in range(0, depth.shape[1], _DEPTH_BLOCK):  # bounded memory: n x block x P points at a time
        block = depth[:, d0:d0 + _DEPTH_BLOCK]
        at = project_in_front(K[u], R[u], t[u], _patch_points(K[v], R[v], t[v], xy, block, config.half))
        out[:, d0:d0 + _DEPTH_BLOCK] = _ncc(own, _sample(images[u], at), config.min_std)
    return out


def inverse_depths(K: np.ndarray, R: np.ndarray, t: np.ndarray, v: int, support: Sequence[int],
                   z_range: Tuple[float, float], step_px: float, max_steps: int) -> np.ndarray:
    """Grid of inverse depths (D,), uniform, fine enough that neighbouring depths differ by
    about ``step_px`` of disparity in the support view farthest from camera v."""
    z_min, z_max = z_range
    centres = camera_centers(R, t)
    baseline = max(float(np.linalg.norm(centres[u] - centres[v])) for u in support)
    steps = int(np.clip(K[v][0, 0] * baseline * (1 / z_min - 1 / z_max) / step_px, 8, max_steps))
    return np.linspace(1 / z_max, 1 / z_min, steps)


def _mean_ncc(images, K, R, t, v, xy, depth, support, config) -> np.ndarray:
    """Mean NCC over the support views of the patches at ``depth`` (n, d); -inf where any
    support view does not count (flat or outside)."""
    scores = np.stack([patch_ncc(images, K, R, t, v, xy, depth, u, config) for u in support])
    counted = np.isfinite(scores).all(axis=0)
    return np.where(counted, scores.mean(axis=0), -np.inf)


def lift(images: Sequence[np.ndarray], K: np.ndarray, R: np.ndarray, t: np.ndarray, v: int, xy: np.ndarray,
         support: Sequence[int], z_range: Tuple[float, float],
         config: SweepConfig = SweepConfig()) -> Tuple[np.ndarray, np.ndarray]:
    """World points of keypoints of view v by plane sweep (module docstring).

    Coarse to fine: a grid of ``coarse_px`` disparity steps finds the peak and tests its
    uniqueness; a grid of ``step_px`` steps within one coarse step either side places it.

    Args:
        images: (H, W) float32 grey images of every view that K, R, t index.
        K, R: (V, 3, 3); t: (V, 3).
        v: the keypoints' view; xy: (n, 2) their pixels.
        support: views compared with view v (at least one; one on either side is best).
        z_range: (nearest, farthest) depth in camera v to search.

    Returns:
        (points, depth): (n, 3) world points and (n,) depths in camera v; NaN where refused.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if not len(support) or not 0 < z_range[0] < z_range[1]:
        raise ValueError(f"need support views and 0 < z_min < z_max, got {list(support)}, {z_range}")
    points, depth = np.full((len(xy), 3), np.nan), np.full(len(xy), np.nan)
    if not len(xy):
        return points, depth
    w = inverse_depths(K, R, t, v, support, z_range, config.coarse_px, config.max_steps)
    mean = _mean_ncc(images, K, R, t, v, xy, np.broadcast_to(1 / w, (len(xy), len(w))), support, config)
    best = mean.argmax(axis=1)
    top = mean[np.arange(len(xy)), best]
    exclusion = max(1, int(round(config.exclusion_px / config.coarse_px)))
    far = np.abs(np.arange(len(w))[None] - best[:, None]) > exclusion
    with np.errstate(invalid="ignore"):  # -inf - -inf where nothing counted: refused either way
        # the coarse peak may sit below the fine one: it needs min_ncc - margin; the fine min_ncc
        ok = (top >= config.min_ncc - config.margin) & (top - np.where(far, mean, -np.inf).max(axis=1) >= config.margin)
    rows = np.flatnonzero(ok)
    if not len(rows):
        return points, depth
    # fine grid: one coarse step either side of the coarse peak
    dw = w[1] - w[0]
    fine = int(np.ceil(2 * config.coarse_px / config.step_px)) + 1
    w_fine = w[best[rows]][:, None] + np.linspace(-dw, dw, fine)[None]
    w_fine = np.clip(w_fine, w[0], w[-1])
    mean_fine = _mean_ncc(images, K, R, t, v, xy[rows], 1 / w_fine, support, config)
    k = mean_fine.argmax(axis=1)
    top_fine = mean_fine[np.arange(len(rows)), k]
    keep = top_fine >= config.min_ncc
    rows, z = rows[keep], 1 / w_fine[np.arange(len(k)), k][keep]
    cam = (np.c_[xy[rows], np.ones(len(rows))] @ np.linalg.inv(K[v]).T) * z[:, None]
    points[rows] = (cam - t[v]) @ R[v]
    depth[rows] = z
    return points, depth
