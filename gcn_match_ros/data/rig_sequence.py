"""Generated rig sequences: a rig of 2–4 cameras moving through a static 3-D scene, with exact
point ids over time (the ground truth of persistent landmarks, :mod:`gcn_match_ros.landmarks`).

The rig drives along +x through a corridor of points (x along the path, |y| up to
``half_width``, height 0–``height``); its cameras share the rig's position and look out at
yaws ``yaw_step_deg`` apart (neighbouring cameras overlap, the outer ones of 3–4 do not). Every window is one capture of all cameras: each visible point's projection plus pixel
noise and a fresh noisy observation of the point's descriptor (the generator of
:mod:`.synthetic`, so the difficulty is calibrated the same way), plus distractors.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Iterator, List, Tuple

import numpy as np

from ..geometry import project
from ..problem import Problem
from .synthetic import DEFAULT_DESCRIPTOR_NOISE, _observe_descriptors, _point_descriptors, distractors, rng_of

__all__ = ["RigSequenceConfig", "rig_sequence", "rig_windows"]


@dataclasses.dataclass(frozen=True)
class RigSequenceConfig:
    """Attributes:
        n_cameras, n_windows: the rig and the sequence length (one window per capture).
        step_m: rig motion per window, metres (with ``yaw_rate_deg`` of turn per window).
        n_points, length_m, half_width_m, height_m: the static scene (points uniform in it).
        yaw_step_deg: yaw between neighbouring cameras (the 77° field of view of the default
            camera overlaps its neighbour's by about half).
        focal_length, image_size, max_depth_m: pinhole cameras; points further away are not seen.
        pixel_noise: keypoint noise std, pixels; descriptor_noise: σ of :mod:`.synthetic`
            (None: its calibrated default for the kind); distractor_fraction of each view.
    """

    n_cameras: int = 3
    n_windows: int = 30
    step_m: float = 0.25
    yaw_rate_deg: float = 0.5
    n_points: int = 3000
    length_m: float = 30.0
    half_width_m: float = 6.0
    height_m: float = 3.0
    yaw_step_deg: float = 40.0
    focal_length: float = 400.0
    image_size: Tuple[int, int] = (640, 480)
    max_depth_m: float = 12.0
    pixel_noise: float = 0.7
    descriptor_kind: str = "sift"
    descriptor_dim: int = 128
    descriptor_noise: float = None
    distractor_fraction: float = 0.2

    @property
    def sigma(self) -> float:
        return DEFAULT_DESCRIPTOR_NOISE[self.descriptor_kind] * 0.8 if self.descriptor_noise is None \
            else self.descriptor_noise


def _rotation_yaw(yaw: float) -> np.ndarray:
    """World->camera rotation of a camera looking along world direction (cos yaw, sin yaw, 0),
    image x to its right, image y down (world z up)."""
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return np.stack([right, down, forward])


def rig_sequence(config: RigSequenceConfig = RigSequenceConfig(), rng=None,
                 start_ns: int = 1_700_000_000 * 10**9, period_ns: int = 10**8) -> Tuple[List[Problem], List[np.ndarray], List[int]]:
    """The windows of one sequence, as lists (:func:`rig_windows`).

    Returns:
        problems: one per window (views = cameras, ``camera_ids`` set, K, R, t of the truth,
            ``gt_track`` = point id for points seen in >= 2 views of the window, else -1);
        point_ids: per window (N,) the true point id of every keypoint (-1: distractor),
            also for points seen by one camera only (they may continue a landmark);
        stamps_ns: the capture time of each window.
    """
    out = list(rig_windows(config, rng, start_ns, period_ns))
    return [p for p, _, _ in out], [i for _, i, _ in out], [s for _, _, s in out]


def rig_windows(config: RigSequenceConfig = RigSequenceConfig(), rng=None, start_ns: int = 1_700_000_000 * 10**9,
                period_ns: int = 10**8) -> Iterator[Tuple[Problem, np.ndarray, int]]:
    """(problem, point ids, stamp) of each window in turn (:func:`rig_sequence`), made as they
    are asked for: an hour-long stream never holds more than one window."""
    cfg = config
    rng = rng_of(rng)
    w, h = cfg.image_size
    K = np.array([[cfg.focal_length, 0, w / 2], [0, cfg.focal_length, h / 2], [0, 0, 1.0]])
    X = np.stack([rng.uniform(-2.0, cfg.length_m, cfg.n_points),
                  rng.uniform(-cfg.half_width_m, cfg.half_width_m, cfg.n_points),
                  rng.uniform(0.0, cfg.height_m, cfg.n_points)], 1)
    raw = _point_descriptors(cfg.descriptor_kind, cfg.n_points, cfg.descriptor_dim, rng)
    yaws = (np.arange(cfg.n_cameras) - (cfg.n_cameras - 1) / 2) * math.radians(cfg.yaw_step_deg)
    cams = [f"cam{c}" for c in range(cfg.n_cameras)]
    # only points within reach are projected (a long stream's corridor holds far more): a visible
    # point has depth under max_depth and lies inside the field of view, so within this distance
    reach = cfg.max_depth_m * math.sqrt(1 + (w / 2 / cfg.focal_length) ** 2 + (h / 2 / cfg.focal_length) ** 2) + 1.0
    by_x = np.argsort(X[:, 0], kind="stable")
    x_sorted = X[by_x, 0]
    for t in range(cfg.n_windows):
        heading = math.radians(cfg.yaw_rate_deg) * t
        centre = np.array([cfg.step_m * t, 0.0, 1.5])
        lo, hi = np.searchsorted(x_sorted, [centre[0] - reach, centre[0] + reach])
        near = np.sort(by_x[lo:hi])
        kps, descs, pids, offsets, Rs, ts = [], [], [], [0], [], []
        for c in range(cfg.n_cameras):
            R = _rotation_yaw(heading + yaws[c])
            tvec = -R @ centre
            uv, z = project(K, R, tvec, X[near])
            visible = np.flatnonzero((z > 0.5) & (z < cfg.max_depth_m) & (uv[:, 0] >= 0) & (uv[:, 0] < w)
                                     & (uv[:, 1] >= 0) & (uv[:, 1] < h))
            seen, uv = near[visible], uv[visible]
            xy = uv + cfg.pixel_noise * rng.standard_normal((seen.size, 2))
            d = _observe_descriptors(cfg.descriptor_kind, raw[seen], cfg.sigma, rng)
            xy_d, d_d = distractors(cfg.descriptor_kind, cfg.descriptor_dim, cfg.sigma, cfg.distractor_fraction,
                                    seen.size, cfg.image_size, 0.0, rng)
            order = rng.permutation(seen.size + xy_d.shape[0])
            kps.append(np.clip(np.concatenate([xy, xy_d])[order], 0, [w - 1, h - 1]))
            descs.append(np.concatenate([d, d_d])[order])
            pids.append(np.concatenate([seen, np.full(xy_d.shape[0], -1)])[order])
            offsets.append(offsets[-1] + order.size)
            Rs.append(R)
            ts.append(tvec)
        pid = np.concatenate(pids).astype(np.int64)
        view = np.repeat(np.arange(cfg.n_cameras), np.diff(offsets))
        views_of = {}
        for p, v in zip(pid[pid >= 0].tolist(), view[pid >= 0].tolist()):
            views_of.setdefault(p, set()).add(v)
        gt = np.array([p if p >= 0 and len(views_of[p]) >= 2 else -1 for p in pid.tolist()], np.int64)
        problem = Problem(view_offsets=np.asarray(offsets), keypoints=np.concatenate(kps).astype(np.float32),
                          descriptors=np.concatenate(descs).astype(np.float32),
                          K=np.repeat(K[None], cfg.n_cameras, 0), R=np.stack(Rs), t=np.stack(ts),
                          image_size=np.repeat(np.array([[w, h]]), cfg.n_cameras, 0), gt_track=gt,
                          name=f"rig{cfg.n_cameras}_w{t}", camera_ids=cams)
        yield problem, pid, start_ns + t * period_ns
