"""Keypoints and descriptors of one image: OpenCV SIFT or ORB, one keypoint per location.

The offline data (``data/convert.py``, ``bags/make.py``) and the live ``feature_node`` detect
with this one function, so the model sees the same keypoints in training and on the robot.
SIFT repeats a location once per orientation peak; only the strongest response within
1.5 px is kept. ORB descriptors are unpacked to 256 columns of 0/1.
"""
from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

__all__ = ["DETECTORS", "DETECTOR_KINDS", "Features", "extract_features"]

DETECTORS = ("sift", "orb")
#: Descriptor kind of each detector: (dimension, binary).
DETECTOR_KINDS = {"sift": (128, False), "orb": (256, True)}
DEDUP_PX = 1.5

class Features(NamedTuple):
    """Keypoints of one image, strongest response first.

    Shapes: keypoints (n, 2) float32 (x, y); descriptors (n, D) float32 (D = 128 SIFT,
    256 ORB bits as 0/1); scales (n,) float32 (OpenCV ``size``); orientations (n,)
    float32 radians.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray
    orientations: np.ndarray



def _dedup(points: np.ndarray, order: np.ndarray, radius: float = DEDUP_PX) -> np.ndarray:
    """Greedy non-maximum suppression: walk ``order`` (strongest first), keep a point unless
    a kept one lies within ``radius``. Returns kept indices in walking order."""
    neighbours = cKDTree(points).query_ball_point(points, r=radius)
    suppressed = np.zeros(len(points), dtype=bool)
    kept = []
    for i in order:
        if suppressed[i]:
            continue
        kept.append(i)
        suppressed[neighbours[i]] = True
    return np.asarray(kept, dtype=np.int64)


def extract_features(image: np.ndarray, detector: str = "sift", max_features: int = 500) -> Features:
    """OpenCV SIFT or ORB, one keypoint per location (strongest response within 1.5 px).

    Ties between keypoints of one location (SIFT's orientation copies share their response)
    keep the first in OpenCV's output order, so the result is deterministic.

    Args:
        image: (H, W) uint8 grayscale or (H, W, 3) BGR.
        detector: 'sift' or 'orb'.
        max_features: passed to the detector (before de-duplication).
    """
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {DETECTORS}, got {detector!r}")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    det = cv2.SIFT_create(max_features) if detector == "sift" else cv2.ORB_create(nfeatures=max_features)
    kps, desc = det.detectAndCompute(image, None)
    dim = DETECTOR_KINDS[detector][0]
    if not kps:
        empty = np.zeros(0, np.float32)
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, dim), np.float32), empty, empty)
    pts = np.array([k.pt for k in kps], dtype=np.float32)
    response = np.array([k.response for k in kps], dtype=np.float32)
    keep = _dedup(pts.astype(np.float64), np.argsort(-response, kind="stable"))
    if detector == "orb":
        desc = np.unpackbits(desc, axis=1)
    return Features(keypoints=pts[keep],
                    descriptors=desc[keep].astype(np.float32),
                    scales=np.array([kps[i].size for i in keep], dtype=np.float32),
                    orientations=np.deg2rad(np.array([kps[i].angle for i in keep], dtype=np.float32)))

