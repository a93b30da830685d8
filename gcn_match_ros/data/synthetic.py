"""Synthetic multi-view matching problems with exact ground truth: a 3D scene seen by
calibrated pinhole cameras.

:func:`random_scene_problem` places cameras (an orbit around an object, or a robot moving
forward), with partial visibility, pixel noise, SIFT-like, Gaussian or ORB-like binary
descriptors, detector scales and orientations, and distractor keypoints; presets
:func:`rome16k`, :func:`partial`, :func:`easy`. It returns a
:class:`~gcn_match_ros.problem.Problem` following ``shared/spec/problem-format.md``;
:func:`write_problems` writes a deterministic batch to ``.npz`` files. The paper's
permutation-noise protocol is :mod:`.permutation_noise`. :func:`mutual_nn_prf` is a small
self-contained calibration helper (precision/recall of plain mutual nearest neighbours on
the descriptors); the project's metrics live elsewhere.

Calibration: plain mutual nearest neighbours on the descriptors (:func:`mutual_nn_prf`,
pooled over 200 problems, seeds 0..199; re-run with ``benchmarks/synthetic_calibration.py``):

=========================  =====  =====  =====  =====================================
preset                      P      R      F1    descriptor noise σ
=========================  =====  =====  =====  =====================================
rome16k(3)                 0.920  0.653  0.764  1.52 (sift default)
rome16k(4)                 0.918  0.650  0.761  1.52
rome16k(3, layout=forward) 0.920  0.652  0.763  1.52
rome16k(3, gaussian)       0.905  0.660  0.763  1.65 (gaussian default)
rome16k(3, binary)         0.905  0.660  0.763  flip 0.28 (binary default; Hamming)
partial(3)                 0.623  0.880  0.730  1.2 (70% visibility, 50% distractors)
partial(3, binary)         0.599  0.924  0.727  flip 0.24
partial(4)                 0.609  0.887  0.722  1.2
easy(3)                    1.000  0.982  0.991  1.0
=========================  =====  =====  =====  =====================================

rome16k matches "nearest neighbours alone F1 0.76 at σ = 1.6" and partial matches
"mutual NN 0.72" of shared/notes/evaluation.md (difficulty matched, not the σ scale).
Generation takes ~2–6 ms per preset problem.

Conventions: world→camera poses ``x ~ K (R X + t)``, OpenCV camera frame (x right,
y down, z forward), pixel (x, y) with the image spanning ``[0, width) × [0, height)``.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable, Optional, Tuple, Union

import numpy as np
from tqdm import tqdm

from ..descriptors import descriptor_kind
from ..geometry import project
from ..problem import Problem, save_problem

__all__ = ["SceneConfig", "random_scene_problem", "rome16k", "partial", "easy", "PRESETS", "preset",
           "DESCRIPTOR_KINDS", "DEFAULT_DESCRIPTOR_NOISE", "sift_normalize", "rng_of", "write_problems",
           "mutual_nn_prf"]

RngLike = Union[None, int, np.random.Generator, np.random.SeedSequence]


def rng_of(rng: RngLike) -> np.random.Generator:
    """``rng`` itself if it is a Generator, else ``np.random.default_rng(rng)``."""
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


# ---------------------------------------------------------------------------------------
# Descriptors
# ---------------------------------------------------------------------------------------
def sift_normalize(desc: np.ndarray, clip: float = 0.2) -> np.ndarray:
    """SIFT's normalisation: L2-normalise, clip every entry at ``clip``, L2-normalise again.

    Shapes: desc (N, D) -> (N, D) float32; all-zero rows stay zero.
    """
    d = np.asarray(desc, dtype=np.float64)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    d = np.minimum(d, clip)
    d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return d.astype(np.float32)


def _l2_normalize(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc, dtype=np.float64)
    return (d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)).astype(np.float32)


# Per-entry standard deviation of the raw point descriptors: Gamma(0.5, 1) for 'sift'
# (like a squared Gaussian: non-negative, most entries small, a few large), N(0, 1) for
# 'gaussian'. Observation noise is expressed in these units.
_SIFT_SHAPE = 0.5
_RAW_STD = {"sift": math.sqrt(_SIFT_SHAPE), "gaussian": 1.0}
DESCRIPTOR_KINDS = ("sift", "gaussian", "binary")
BINARY_FLIP = 0.28

#: Descriptor noise σ (in units of the raw point-descriptor std) of the ``rome16k``
#: preset, calibrated so that plain mutual nearest neighbours score F1 ≈ 0.76
#: (3–4 views, p = 80), like the σ = 1.6 setting of shared/notes/evaluation.md
#: (its scale differs from ours; only the resulting difficulty was matched).
#: For 'binary' the noise is the probability that an observation flips a bit of its
#: point's code, calibrated the same way (mutual NN by Hamming distance F1 ≈ 0.76).
DEFAULT_DESCRIPTOR_NOISE = {"sift": 1.52, "gaussian": 1.65, "binary": BINARY_FLIP}


def _point_descriptors(kind: str, n: int, dim: int, rng: np.random.Generator) -> np.ndarray:
    """Raw (un-normalised) descriptors of ``n`` scene points. Shapes: -> (n, dim) float64."""
    if kind == "binary":
        return (rng.random((n, dim)) < 0.5).astype(np.float64)
    if kind == "sift":
        return rng.gamma(_SIFT_SHAPE, 1.0, size=(n, dim))
    return rng.standard_normal((n, dim))


def distractors(kind: str, dim: int, sigma: float, fraction: float, n_seen: int, image_size: Tuple[int, int],
                border_px: float, rng: np.random.Generator) -> Tuple[np.ndarray, np.ndarray]:
    """Keypoints that image no scene point, ``fraction`` of a view's keypoints beside its
    ``n_seen`` true ones: uniform in the image (``border_px`` from its edges), each with a noisy
    observation of its own random descriptor.

    Shapes: -> uv (n_d, 2) pixels, descriptors (n_d, dim) float32.
    """
    w, h = image_size
    n_d = int(round(fraction / (1.0 - fraction) * n_seen)) if fraction > 0 else 0
    uv = np.stack([rng.uniform(border_px, w - 1 - border_px, n_d), rng.uniform(border_px, h - 1 - border_px, n_d)],
                  axis=1)
    return uv, _observe_descriptors(kind, _point_descriptors(kind, n_d, dim, rng), sigma, rng)


def _observe_descriptors(kind: str, raw: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """One noisy observation of each raw descriptor, normalised like the detector would.

    'sift': add N(0, (σ·std)²), rectify at 0 (histograms are non-negative), SIFT-normalise.
    'gaussian': add N(0, (σ·std)²), L2-normalise.
    'binary': flip each bit with probability σ (0/1 floats, like ORB's unpacked bits).
    Shapes: raw (n, D) -> (n, D) float32.
    """
    if kind == "binary":
        return np.logical_xor(raw > 0.5, rng.random(raw.shape) < sigma).astype(np.float32)
    noisy = raw + sigma * _RAW_STD[kind] * rng.standard_normal(raw.shape)
    if kind == "sift":
        noisy = np.maximum(noisy, 0.0)
        # A fully rectified row (vanishingly rare) would be all-zero: keep its strongest bin.
        empty = ~np.any(noisy > 0, axis=1)
        if np.any(empty):
            noisy[empty, np.argmax(raw[empty], axis=1)] = 1.0
        return sift_normalize(noisy)
    return _l2_normalize(noisy)


# ---------------------------------------------------------------------------------------
# 3D scene generator
# ---------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """A random 3D scene seen by ``n_views`` calibrated pinhole cameras.

    Geometry:
        layout: "orbit" — cameras on a sphere cap at ``camera_distance`` around an object
            (points ~ N(0, object_std²) in 3D), azimuths spread over ``arc_deg``, elevations in
            ``elevation_deg``, each looking at the object centre (jitter ``look_jitter``);
            "forward" — a robot moving along +x in steps of ``forward_step`` (lateral / height /
            yaw jitter), points in front at depths ``depth_range`` of the last camera.
            In both, every scene point lies in front of and inside (``border_px`` margin) the
            image of *every* camera, so what a view sees is decided by ``visibility`` alone.
        image_size: (width, height) pixels; focal_length: pixels (fx = fy), principal point
            at the image centre.
        roll_deg: std of each camera's rotation about its optical axis (also rotates the
            keypoint orientations of that view).
    Observations:
        visibility: probability that a view sees a point (independently). Every point is
            then made visible in at least ``min_views`` views (extra views drawn at random),
            so the realised fraction is a little higher than ``visibility`` when it is low.
            ``min_views = 1`` allows points seen once (their gt_track is -1).
        pixel_noise: std of the Gaussian noise added to projected keypoints, pixels
            (keypoints are then clipped into the image).
        distractor_fraction: fraction of each view's keypoints that image no scene point
            (uniform location, their own random descriptor; gt_track -1). Must be < 1.
        descriptor_kind: "sift" (non-negative, sparse-ish, L2-normalised, clipped at 0.2 and
            renormalised), "gaussian" (L2-normalised Gaussian) or "binary" (random bits as
            0/1 floats, like ORB's 256 unpacked bits).
        descriptor_dim: 128 for SIFT-like descriptors, 256 for ORB-like ones.
        descriptor_noise: per-observation noise σ in units of the point descriptor's
            per-entry std ("binary": the probability of flipping a bit); None =
            :data:`DEFAULT_DESCRIPTOR_NOISE` of the kind (calibrated).
        scale_median, scale_log_std: log-normal detector scale (pixels) of each point at the
            reference depth; an observation's scale = point scale × reference depth / depth ×
            exp(N(0, scale_view_log_std²)).
        orientation_noise_deg: std of the per-observation orientation noise; orientation =
            point orientation (uniform) − camera roll + noise, wrapped to (−π, π].
    """

    n_views: int = 3
    n_points: int = 80
    layout: str = "orbit"
    image_size: Tuple[int, int] = (640, 480)
    focal_length: float = 500.0
    camera_distance: float = 4.0
    object_std: float = 0.6
    arc_deg: float = 60.0
    elevation_deg: Tuple[float, float] = (0.0, 30.0)
    look_jitter: float = 0.1
    forward_step: float = 0.5
    depth_range: Tuple[float, float] = (2.0, 12.0)
    roll_deg: float = 5.0
    border_px: float = 8.0
    visibility: float = 1.0
    min_views: int = 2
    pixel_noise: float = 1.0
    distractor_fraction: float = 0.0
    descriptor_kind: str = "sift"
    descriptor_dim: int = 128
    descriptor_noise: Optional[float] = None
    scale_median: float = 4.0
    scale_log_std: float = 0.5
    scale_view_log_std: float = 0.1
    orientation_noise_deg: float = 5.0

    def __post_init__(self) -> None:
        if self.n_views < 1 or self.n_points < 1:
            raise ValueError("SceneConfig: n_views and n_points must be >= 1")
        if self.layout not in ("orbit", "forward"):
            raise ValueError(f"SceneConfig.layout must be 'orbit' or 'forward', got {self.layout!r}")
        if self.descriptor_kind not in DESCRIPTOR_KINDS:
            raise ValueError(f"SceneConfig.descriptor_kind must be one of {DESCRIPTOR_KINDS}, "
                             f"got {self.descriptor_kind!r}")
        if self.descriptor_kind == "binary" and self.descriptor_noise is not None \
                and not 0.0 <= self.descriptor_noise <= 0.5:
            raise ValueError(f"SceneConfig.descriptor_noise of binary descriptors is a bit-flip probability "
                             f"in [0, 0.5], got {self.descriptor_noise}")
        if not 0.0 <= self.visibility <= 1.0:
            raise ValueError(f"SceneConfig.visibility must be in [0, 1], got {self.visibility}")
        if not 0.0 <= self.distractor_fraction < 1.0:
            raise ValueError(f"SceneConfig.distractor_fraction must be in [0, 1), got {self.distractor_fraction}")
        if self.min_views not in (1, 2):
            raise ValueError(f"SceneConfig.min_views must be 1 or 2, got {self.min_views}")
        if self.min_views > self.n_views:
            raise ValueError("SceneConfig.min_views exceeds n_views")
        if self.pixel_noise < 0 or (self.descriptor_noise is not None and self.descriptor_noise < 0):
            raise ValueError("SceneConfig: noise levels must be >= 0")
        w, h = self.image_size
        if w <= 2 * self.border_px or h <= 2 * self.border_px:
            raise ValueError("SceneConfig.image_size too small for border_px")

    @property
    def sigma(self) -> float:
        """The descriptor noise actually used."""
        if self.descriptor_noise is not None:
            return float(self.descriptor_noise)
        return DEFAULT_DESCRIPTOR_NOISE[self.descriptor_kind]

    def replace(self, **changes) -> "SceneConfig":
        return dataclasses.replace(self, **changes)


def rome16k(n_views: int = 3, descriptor_kind: str = "sift", **changes) -> SceneConfig:
    """The paper's Rome16K-style setting: 3 or 4 views, p = 80 points seen by every view,
    no distractors, descriptors at the calibrated noise of their kind (mutual-NN F1 ≈ 0.76)."""
    return SceneConfig(n_views=n_views, n_points=80, visibility=1.0, distractor_fraction=0.0,
                       descriptor_kind=descriptor_kind, **_descriptor(descriptor_kind)).replace(**changes)


def partial(n_views: int = 3, descriptor_kind: str = "sift", **changes) -> SceneConfig:
    """Partial visibility and clutter: each view sees ~70% of the points (each point in
    ≥ 2 views) and half of every view's keypoints are distractors.

    Descriptor noise σ = 1.2 (not the rome16k 1.52; binary: flip 0.24, not 0.28): calibrated
    so that plain mutual NN scores F1 ≈ 0.72, the figure shared/notes/evaluation.md reports
    for this setting. Here the errors are false positives (distractors and points the other
    view does not see always find *some* mutual neighbour): P ≈ 0.62, R ≈ 0.88. With
    σ = 1.52 F1 drops to ≈ 0.52.
    """
    return SceneConfig(n_views=n_views, n_points=80, visibility=0.7, distractor_fraction=0.5,
                       descriptor_kind=descriptor_kind,
                       **_descriptor(descriptor_kind, {"sift": 1.2, "binary": 0.24})).replace(**changes)


def easy(n_views: int = 3, descriptor_kind: str = "sift", **changes) -> SceneConfig:
    """Low descriptor (σ = 1.0; binary: flip 0.2) and pixel noise, everything visible:
    mutual NN F1 ≈ 0.99."""
    return SceneConfig(n_views=n_views, n_points=80, visibility=1.0, distractor_fraction=0.0,
                       descriptor_kind=descriptor_kind, pixel_noise=0.5,
                       **_descriptor(descriptor_kind, {"sift": 1.0, "binary": 0.2})).replace(**changes)


def _descriptor(kind: str, noise: Optional[dict] = None) -> dict:
    """SceneConfig fields of a preset's descriptors: the kind's dimension (ORB-like binary
    codes are 256 bits) and the preset's noise for that kind (None: the calibrated default)."""
    return {"descriptor_dim": 256 if kind == "binary" else 128,
            "descriptor_noise": (noise or {}).get(kind)}


#: The scene presets by name (``gcn-match synth --preset``, ``synth:PRESET`` data specs).
PRESETS = {"rome16k": rome16k, "partial": partial, "easy": easy}


def preset(name: str, n_views: int, descriptor_kind: str = "sift") -> SceneConfig:
    """The scene preset ``name`` (:data:`PRESETS`) with ``n_views`` views and descriptors of
    ``descriptor_kind``; a ValueError names the choices for an unknown preset or descriptor."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset '{name}'; choose one of {', '.join(PRESETS)}")
    if descriptor_kind not in DESCRIPTOR_KINDS:
        raise ValueError(f"unknown descriptor '{descriptor_kind}'; choose one of {', '.join(DESCRIPTOR_KINDS)}")
    return PRESETS[name](n_views, descriptor_kind=descriptor_kind)


def _look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray, roll: float) -> np.ndarray:
    """World→camera rotation of a camera at ``center`` looking at ``target`` (OpenCV frame:
    z forward, y down), rotated by ``roll`` radians about its optical axis."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z])


def _cameras(cfg: SceneConfig, rng: np.random.Generator):
    """Poses (R (V,3,3), t (V,3)), rolls (V,), and the reference depth for scales."""
    V = cfg.n_views
    up = np.array([0.0, 0.0, 1.0])
    rolls = np.deg2rad(cfg.roll_deg) * rng.standard_normal(V)
    Rs, ts = np.zeros((V, 3, 3)), np.zeros((V, 3))
    if cfg.layout == "orbit":
        az = np.deg2rad(cfg.arc_deg) * (rng.random(V) - 0.5)
        el = np.deg2rad(rng.uniform(cfg.elevation_deg[0], cfg.elevation_deg[1], V))
        for v in range(V):
            c = cfg.camera_distance * np.array([math.cos(el[v]) * math.cos(az[v]),
                                                math.cos(el[v]) * math.sin(az[v]), math.sin(el[v])])
            target = cfg.look_jitter * rng.standard_normal(3)
            Rs[v] = _look_at(c, target, up, rolls[v])
            ts[v] = -Rs[v] @ c
        ref_depth = cfg.camera_distance
    else:
        for v in range(V):
            c = np.array([v * cfg.forward_step * (1.0 + 0.2 * (rng.random() - 0.5)),
                          0.1 * rng.standard_normal(), 0.05 * rng.standard_normal()])
            yaw, pitch = np.deg2rad(5.0) * rng.standard_normal(), np.deg2rad(2.0) * rng.standard_normal()
            d = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
            Rs[v] = _look_at(c, c + d, up, rolls[v])
            ts[v] = -Rs[v] @ c
        ref_depth = 0.5 * (cfg.depth_range[0] + cfg.depth_range[1])
    return Rs, ts, rolls, ref_depth


def _intrinsics(cfg: SceneConfig) -> np.ndarray:
    w, h = cfg.image_size
    K = np.array([[cfg.focal_length, 0.0, w / 2.0], [0.0, cfg.focal_length, h / 2.0], [0.0, 0.0, 1.0]])
    return np.repeat(K[None], cfg.n_views, axis=0)


def _inside(cfg: SceneConfig, uv: np.ndarray, z: np.ndarray) -> np.ndarray:
    w, h = cfg.image_size
    b = cfg.border_px
    return ((z > 0.1) & np.isfinite(uv).all(axis=1) & (uv[:, 0] >= b) & (uv[:, 0] <= w - 1 - b)
            & (uv[:, 1] >= b) & (uv[:, 1] <= h - 1 - b))


def _sample_points(cfg: SceneConfig, K, Rs, ts, rng: np.random.Generator) -> np.ndarray:
    """``n_points`` world points in front of and inside every camera (rejection sampling)."""
    n = cfg.n_points
    out = []
    have = 0
    for _ in range(200):
        m = max(4 * (n - have), 64)
        if cfg.layout == "orbit":
            X = cfg.object_std * rng.standard_normal((m, 3))
        else:
            # Back-project random pixels of the last (most advanced) camera at random depths.
            w, h = cfg.image_size
            uv1 = np.stack([rng.uniform(0, w, m), rng.uniform(0, h, m), np.ones(m)], axis=1)
            rays = uv1 @ np.linalg.inv(K[-1]).T
            depth = rng.uniform(cfg.depth_range[0], cfg.depth_range[1], m)
            Xc = rays * depth[:, None]
            X = (Xc - ts[-1]) @ Rs[-1]  # R^T (Xc - t)
        ok = np.ones(m, bool)
        for v in range(cfg.n_views):
            uv, z = project(K[v], Rs[v], ts[v], X)
            ok &= _inside(cfg, uv, z)
        X = X[ok]
        take = min(n - have, X.shape[0])
        out.append(X[:take])
        have += take
        if have == n:
            return np.concatenate(out)
    raise RuntimeError("SceneConfig: could not place points inside every camera's image; "
                       "widen the field of view or shrink the scene")


def _visibility(cfg: SceneConfig, rng: np.random.Generator) -> np.ndarray:
    """(V, P) bool: which view sees which point; each point in >= min_views views."""
    V, P = cfg.n_views, cfg.n_points
    vis = rng.random((V, P)) < cfg.visibility
    count = vis.sum(axis=0)
    for p in np.flatnonzero(count < cfg.min_views):
        need = cfg.min_views - count[p]
        unseen = np.flatnonzero(~vis[:, p])
        vis[rng.choice(unseen, size=need, replace=False), p] = True
    return vis


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * a))


def random_scene_problem(config: SceneConfig = SceneConfig(), rng: RngLike = None, name: str = "") -> Problem:
    """A random scene seen by ``config.n_views`` cameras, as a :class:`Problem`.

    Keypoints are the projections ``x ~ K (R X + t)`` plus pixel noise (inside the image);
    descriptors are the point's descriptor plus per-observation noise, normalised like
    SIFT; ``gt_track`` is the scene point id (>= 0) for points seen in >= 2 views and -1
    for points seen once and for distractors. Views are stored one after another with the
    keypoints of each view in random order. Deterministic given ``rng``.
    """
    cfg = config
    rng = rng_of(rng)
    V, P = cfg.n_views, cfg.n_points
    w, h = cfg.image_size
    K = _intrinsics(cfg)
    Rs, ts, rolls, ref_depth = _cameras(cfg, rng)
    X = _sample_points(cfg, K, Rs, ts, rng)
    vis = _visibility(cfg, rng)
    n_seen = vis.sum(axis=0)

    raw = _point_descriptors(cfg.descriptor_kind, P, cfg.descriptor_dim, rng)
    point_scale = cfg.scale_median * np.exp(cfg.scale_log_std * rng.standard_normal(P))
    point_ori = rng.uniform(-math.pi, math.pi, P)
    ori_noise = np.deg2rad(cfg.orientation_noise_deg)
    sigma = cfg.sigma

    kps, descs, scales, oris, gts, offsets = [], [], [], [], [], [0]
    for v in range(V):
        pts = np.flatnonzero(vis[v])
        uv, z = project(K[v], Rs[v], ts[v], X[pts])
        uv = uv + cfg.pixel_noise * rng.standard_normal(uv.shape)
        d = _observe_descriptors(cfg.descriptor_kind, raw[pts], sigma, rng)
        s = point_scale[pts] * ref_depth / z * np.exp(cfg.scale_view_log_std * rng.standard_normal(pts.size))
        o = point_ori[pts] - rolls[v] + ori_noise * rng.standard_normal(pts.size)
        g = np.where(n_seen[pts] >= 2, pts, -1)

        uv_d, d_d = distractors(cfg.descriptor_kind, cfg.descriptor_dim, sigma, cfg.distractor_fraction, pts.size,
                                cfg.image_size, cfg.border_px, rng)
        n_d = uv_d.shape[0]
        if n_d:
            s_d = cfg.scale_median * np.exp(cfg.scale_log_std * rng.standard_normal(n_d))
            o_d = rng.uniform(-math.pi, math.pi, n_d)
            uv, d = np.concatenate([uv, uv_d]), np.concatenate([d, d_d])
            s, o = np.concatenate([s, s_d]), np.concatenate([o, o_d])
            g = np.concatenate([g, np.full(n_d, -1)])

        order = rng.permutation(g.size)
        uv = np.stack([np.clip(uv[:, 0], 0.0, w - 1.0), np.clip(uv[:, 1], 0.0, h - 1.0)], axis=1)
        kps.append(uv[order]); descs.append(d[order]); scales.append(s[order])
        oris.append(_wrap(o[order])); gts.append(g[order])
        offsets.append(offsets[-1] + g.size)

    return Problem(
        view_offsets=np.asarray(offsets, np.int64),
        keypoints=np.concatenate(kps).astype(np.float32),
        descriptors=np.concatenate(descs).astype(np.float32),
        scales=np.concatenate(scales).astype(np.float32),
        orientations=np.concatenate(oris).astype(np.float32),
        K=K, R=Rs, t=ts,
        image_size=np.repeat(np.array([[w, h]], np.int64), V, axis=0),
        gt_track=np.concatenate(gts).astype(np.int64),
        name=name,
    )


# ---------------------------------------------------------------------------------------
# Calibration helper and batch writer
# ---------------------------------------------------------------------------------------
def mutual_nn_prf(problem: Problem) -> Tuple[float, float, float, int, int, int]:
    """Precision, recall, F1 of plain mutual nearest neighbours (cosine of L2-normalised
    descriptors; Hamming distance of 0/1 ones) over all view pairs, and the counts (true
    positives, predicted, true pairs).

    A pair of keypoints in different views is true when both gt_track are equal and >= 0;
    keypoints labelled -2 are left out. Needs ``problem.gt_track``.
    """
    gt = problem.gt_track
    binary = descriptor_kind(problem.descriptors)[1]
    # for 0/1 codes a·b - (|a| + |b|) / 2 = -Hamming / 2: the same ranking as Hamming
    d = np.asarray(problem.descriptors, np.float64) if binary else _l2_normalize(problem.descriptors)
    half = d.sum(axis=1) / 2 if binary else np.zeros(len(d))
    offs = problem.view_offsets
    tp = pred = true = 0
    for i in range(problem.n_views):
        for j in range(i + 1, problem.n_views):
            gi, gj = gt[offs[i]:offs[i + 1]], gt[offs[j]:offs[j + 1]]
            li, lj = gi != -2, gj != -2
            gi, gj = gi[li], gj[lj]
            true += np.intersect1d(gi[gi >= 0], gj[gj >= 0]).size
            if gi.size == 0 or gj.size == 0:
                continue
            s = d[offs[i]:offs[i + 1]][li] @ d[offs[j]:offs[j + 1]][lj].T
            s -= half[offs[i]:offs[i + 1]][li][:, None] + half[offs[j]:offs[j + 1]][lj][None, :]
            a = s.argmax(axis=1)
            b = s.argmax(axis=0)
            r = np.flatnonzero(b[a] == np.arange(gi.size))
            pred += r.size
            tp += int(np.sum((gi[r] == gj[a[r]]) & (gi[r] >= 0)))
    p = tp / pred if pred else 0.0
    rc = tp / true if true else 0.0
    f1 = 2 * p * rc / (p + rc) if p + rc > 0 else 0.0
    return p, rc, f1, tp, pred, true


def write_problems(out_dir, generator: Callable[[np.random.Generator], object], count: int,
                   seed: int = 0, prefix: str = "synthetic", progress: bool = True) -> list:
    """Write ``count`` problems ``{out_dir}/{prefix}-{i:05d}.npz`` with :func:`save_problem`.

    ``generator(rng)`` returns a :class:`Problem` (or a tuple whose first item is one, as
    :func:`.permutation_noise.permutation_noise_problem` does), e.g.
    ``lambda rng: random_scene_problem(rome16k(3), rng)``. Problem i uses its own
    generator from ``SeedSequence(seed).spawn(count)[i]``, so the files are a deterministic
    function of ``seed`` and i. Returns the written paths.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    children = np.random.SeedSequence(seed).spawn(count)
    paths = []
    for i, child in enumerate(tqdm(children, desc=f"writing {prefix}", unit="problem", disable=not progress)):
        prob = generator(np.random.default_rng(child))
        if isinstance(prob, tuple):
            prob = prob[0]
        path = out_dir / f"{prefix}-{i:05d}.npz"
        prob.name = path.stem
        save_problem(prob, path)
        paths.append(path)
    return paths
