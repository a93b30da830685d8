"""Per-keypoint input features of the GCN.

The paper's node features (Phillips & Daniilidis 2019, Sec. 5.2) are the
L2-normalised SIFT descriptor followed by the calibrated image coordinates, the
log detector scale and the orientation. With a D-dimensional descriptor every part
enabled gives F = D + 4 columns, in this order::

    [ descriptor (D) | x, y (2) | log(scale) - 1.5 (1) | orientation / pi (1) ]

Missing optional inputs (no ``scales`` / ``orientations`` in the problem) give
zero columns, never fewer columns, so F depends only on D and the
:class:`FeatureConfig` and one trained model serves every problem with that
descriptor.
"""
from __future__ import annotations

import dataclasses
import numpy as np

from .configs import JsonConfig
from .descriptors import NORMALIZATIONS, normalize_descriptors
from .geometry import unproject
from .problem import Problem

__all__ = ["FeatureConfig", "node_features", "feature_dim", "calibrated_points", "normalized_positions"]


@dataclasses.dataclass(frozen=True)
class FeatureConfig(JsonConfig):
    """Which parts of the node features are included.

    Attributes:
        descriptor: the row-normalised descriptor (D columns).
        normalization: "l2" or "rootsift", as :func:`descriptors.normalize_descriptors`.
        position: calibrated x, y (2 columns); see :func:`normalized_positions`.
        scale: log(scale) - 1.5 (1 column; 0 where scales are missing or <= 0).
        orientation: orientation / pi (1 column; 0 where missing).
    """

    descriptor: bool = True
    normalization: str = "l2"
    position: bool = True
    scale: bool = True
    orientation: bool = True

    def __post_init__(self) -> None:
        if self.normalization not in NORMALIZATIONS:
            raise ValueError(f"FeatureConfig.normalization must be one of {NORMALIZATIONS}, "
                             f"got {self.normalization!r}")



def feature_dim(descriptor_dim: int, config: FeatureConfig = FeatureConfig()) -> int:
    """Number of feature columns F for descriptors of dimension ``descriptor_dim``."""
    return (int(descriptor_dim) * config.descriptor + 2 * config.position
            + int(config.scale) + int(config.orientation))


def calibrated_points(problem: Problem) -> np.ndarray:
    """Homogeneous normalised image coordinates K_v^-1 [x, y, 1] of every keypoint.

    The result is scaled so that its last coordinate is 1 (it already is for the
    usual upper-triangular K). Used by :func:`gcn_match_ros.learn.losses.epipolar_loss`.

    Shapes:
        problem.keypoints (N, 2), problem.K (V, 3, 3) -> (N, 3) float64.

    Raises:
        ValueError: the problem has no intrinsics ``K``.
    """
    if problem.K is None:
        raise ValueError("calibrated_points: the problem has no intrinsics 'K'")
    out = np.zeros((problem.n_keypoints, 3), np.float64)
    for v in range(problem.n_views):
        sl = problem.view_slice(v)
        if sl.stop > sl.start:
            out[sl] = unproject(problem.K[v], problem.keypoints[sl])
    return out


def normalized_positions(problem: Problem) -> np.ndarray:
    """Keypoint positions in a resolution-free frame, one view at a time.

    - with intrinsics: calibrated coordinates, the first two entries of K^-1 [x, y, 1];
    - else with ``image_size`` (w, h): ((x - w/2), (y - h/2)) / max(w, h), in [-0.5, 0.5];
    - else: centred on the middle of the view's keypoint bounding box and divided by
      its larger side (a view with a single keypoint, or none spread, maps to 0).

    Shapes: problem.keypoints (N, 2) -> (N, 2) float32.
    """
    kp = problem.keypoints.astype(np.float64)
    out = np.zeros_like(kp)
    for v in range(problem.n_views):
        sl = problem.view_slice(v)
        pts = kp[sl]
        if pts.shape[0] == 0:
            continue
        if problem.K is not None:
            out[sl] = unproject(problem.K[v], pts)[:, :2]
        elif problem.image_size is not None:
            wh = problem.image_size[v].astype(np.float64)
            out[sl] = (pts - wh / 2.0) / max(float(wh.max()), 1.0)
        else:
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            extent = float((hi - lo).max())
            out[sl] = (pts - (lo + hi) / 2.0) / (extent if extent > 0 else 1.0)
    return out.astype(np.float32)


def node_features(problem: Problem, config: FeatureConfig = FeatureConfig()) -> np.ndarray:
    """Input features of every keypoint of ``problem``.

    Columns (each part only if enabled in ``config``)::

        normalised descriptor (D) | x, y | log(scale) - 1.5 | orientation / pi

    Shapes:
        problem: N keypoints with D-dimensional descriptors -> (N, F) float32,
        F = :func:`feature_dim` (D, config).
    """
    n = problem.n_keypoints
    parts = []
    if config.descriptor:
        parts.append(normalize_descriptors(problem.descriptors, config.normalization))
    if config.position:
        parts.append(normalized_positions(problem))
    if config.scale:
        col = np.zeros((n, 1), np.float32)
        if problem.scales is not None:
            s = problem.scales.astype(np.float64)
            ok = s > 0
            col[ok, 0] = np.log(s[ok]) - 1.5
        parts.append(col)
    if config.orientation:
        col = np.zeros((n, 1), np.float32)
        if problem.orientations is not None:
            col[:, 0] = problem.orientations / np.pi
        parts.append(col)
    if not parts:
        return np.zeros((n, 0), np.float32)
    return np.ascontiguousarray(np.concatenate(parts, axis=1), dtype=np.float32)
