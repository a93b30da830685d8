"""Pose-free two-view geometric verification (OpenCV USAC-MAGSAC).

Per view pair a homography H and a fundamental matrix F are fitted on seed pairs
(pixel coordinates); residuals of any pair are then measured in pixels:
symmetric transfer error for H, Sampson distance for F. Used at test time by the
``nn-ransac`` baseline and by the learned edge scorer's features; never uses poses.
"""
from __future__ import annotations

import dataclasses
from typing import Optional, Tuple

import cv2
import numpy as np

from ..geometry import sampson_distance, transfer

__all__ = ["PairModel", "fit_pair", "residuals", "MIN_SEEDS", "RANSAC_PX", "PLANAR_RATIO"]

MIN_SEEDS = 12
RANSAC_PX = 3.0
PLANAR_RATIO = 0.8  # H inliers >= this x F inliers: the pair is treated as planar


@dataclasses.dataclass
class PairModel:
    """H and/or F; ``planar``: the homography explains the seeds about as well as F
    (ORB-SLAM-style model selection), then only H is used for residuals and guidance."""
    H: Optional[np.ndarray]
    F: Optional[np.ndarray]
    planar: bool = False

    def selected(self) -> "PairModel":
        return PairModel(self.H, None, True) if self.planar else PairModel(None, self.F, False)


def fit_pair(xa: np.ndarray, xb: np.ndarray, px: float = RANSAC_PX, seed: int = 0) -> Optional[PairModel]:
    """H and F (each None if it fails or is poorly supported) from seed pairs xa[i] <-> xb[i]."""
    if xa.shape[0] < MIN_SEEDS:
        return None
    a = np.ascontiguousarray(xa, np.float64)
    b = np.ascontiguousarray(xb, np.float64)
    cv2.setRNGSeed(seed)
    H = F = None
    try:
        H, mh = cv2.findHomography(a, b, cv2.USAC_MAGSAC, px, maxIters=2000, confidence=0.999)
        if H is None or mh is None or int(mh.sum()) < 8 or abs(np.linalg.det(H)) < 1e-8:
            H = None
    except cv2.error:
        H = None
    try:
        F, mf = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, px / 2, 0.999, 2000)
        if F is None or F.shape != (3, 3) or mf is None or int(mf.sum()) < 12:
            F = None
    except cv2.error:
        F = None
    if H is None and F is None:
        return None
    nh = int(mh.sum()) if H is not None else 0
    nf = int(mf.sum()) if F is not None else 0
    planar = H is not None and (F is None or nh >= PLANAR_RATIO * nf)
    if not planar and F is None:
        return None
    return PairModel(H, F, planar)


def residuals(model: PairModel, xa: np.ndarray, xb: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(H symmetric transfer error, F Sampson distance) in pixels; inf where a model is missing."""
    n = xa.shape[0]
    rh = np.full(n, np.inf)
    rf = np.full(n, np.inf)
    if model.H is not None:
        try:
            Hi = np.linalg.inv(model.H)
            rh = 0.5 * (np.linalg.norm(transfer(model.H, xa) - xb, axis=1)
                        + np.linalg.norm(transfer(Hi, xb) - xa, axis=1))
        except np.linalg.LinAlgError:
            pass
    if model.F is not None:
        rf = sampson_distance(model.F, xa, xb)
    return rh, rf
