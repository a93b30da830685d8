"""Pose-free two-view geometric verification (OpenCV USAC), and when to trust it.

Per view pair a homography H and an epipolar model are fitted on seed pairs: a fundamental
matrix F from pixels, or — when both cameras' intrinsics are known (a calibrated robot's
``camera_info``) — an essential matrix E from calibrated points (5 degrees of freedom
instead of 7, points behind either camera rejected), turned into F = K_b⁻ᵀ E K_a⁻¹ so every
residual stays in pixels: symmetric transfer error for H, Sampson distance for F.

The epipolar model's fit threshold follows the keypoints' localisation. SIFT on real images
localises to 0.1-0.4 px; fitted at 2 px, a model there also explains repetitions shifted a few
pixels off the true epipolar lines and tilts its lines towards them (castle-P19: ~4 degrees, a
third of a view pair's pairs wrong). So F is fitted first at ``fine_px`` (0.5 px) and kept when
it explains at least half of the seeds (:data:`FINE_MIN_INLIER_RATIO`, and at least
:data:`MIN_INLIERS`) and the seeds show sub-pixel localisation: at least :data:`FINE_SHARE` of
those within ``epipolar_px`` of the fine model lie within ``fine_px`` (Gaussian noise of sigma
gives ~erf(0.35 / sigma) / erf(1.41 / sigma): 0.99 at 0.2 px, 0.68 at 0.5 px; measured per view
pair on the windows of benchmarks/geometric_eval.py: SIFT 0.72-1.0; generated scenes with 1 px of
noise 0.54-0.77). Otherwise F is fitted again at ``epipolar_px``. Repetitions 2-10 px off the
true lines lie beyond the fine model's ``epipolar_px`` and do not count against it.

A fitted model is not yet a *trusted* one. A model fitted to a view pair that shares no
scene (cameras pointing different ways) or to a repetitive facade still finds a handful of
"inliers": 7 seeds always fit a fundamental matrix exactly. :meth:`PairModel.trusted` asks
for at least ``min_inliers`` inliers making at least ``min_inlier_ratio`` of the seeds. Only
trusted models guide candidates, give geometric features and check tracks
(:mod:`.candidates`, :mod:`.consistency`). Never uses poses.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Optional, Tuple

import cv2
import numba
import numba.extending
import numpy as np

from ..geometry import sampson_distance, unproject

__all__ = ["PairModel", "fit_pair", "may_be_trusted", "residuals", "model_matrices", "matrix_residuals", "trusted_support", "MIN_SEEDS", "RANSAC_PX", "EPIPOLAR_PX", "FINE_PX",
           "FINE_SHARE", "FINE_MIN_INLIER_RATIO", "PLANAR_RATIO", "MIN_INLIERS", "MIN_INLIER_RATIO", "AGREE_SIGMAS", "AGREE_MIN_PX",
           "transfer_error_px", "sampson_error_px"]

MIN_SEEDS = 12
RANSAC_PX = 3.0         # inlier threshold of the homography (symmetric transfer error)
EPIPOLAR_PX = 2.0       # inlier threshold of the epipolar model's fit (Sampson distance)
FINE_PX = 0.5           # ... tried first, for keypoints localised to a fraction of a pixel
FINE_SHARE = 0.72       # ... kept when this share of the seeds within EPIPOLAR_PX is within it
#: ... and when it explains at least half of all the seeds. Fitted below the keypoints' noise,
#: RANSAC with local optimisation can bend a model onto a subset of ~40 seeds that then looks
#: sub-pixel by the share test: on generated scenes with 1 px of noise 9 of 465 view pairs kept
#: such a fine model (41-54 % of their seeds), which refused most of their true pairs (agreement
#: within 0.5 px) and split every track through them. Sub-pixel keypoints put most seeds within
#: a fine model: of the 338 real SIFT fine models of benchmarks/geometric_eval.py's windows, 12
#: explain less than half (entry-P10, castle-P19) and are fitted at EPIPOLAR_PX instead.
FINE_MIN_INLIER_RATIO = 0.5
#: RANSAC iterations of the fine fit: enough for the inlier shares of sub-pixel keypoints
#: (0.999 confidence: ~250 at 60 % for F's 7 points); noisy keypoints' fine fits, which fail,
#: stop there instead of running the full count
FINE_MAX_ITERS = 250
ESSENTIAL_MAX_ITERS = 1000  # OpenCV's default for the essential matrix
#: A pair agrees with an epipolar model within 3 sigma of the keypoint noise, sigma estimated
#: from the fit's inliers (median Sampson distance / 0.674, as for a half-normal), clipped to
#: [AGREE_MIN_PX, the fit's threshold]: ~1 px for SIFT on real images (well inside the 2 px
#: a match may be off the true lines), up to 2 px for noisier keypoints.
AGREE_SIGMAS, AGREE_MIN_PX = 3.0, 1.0
#: H inliers >= this x F inliers: the pair is treated as planar. A model may store another
#: (EdgeConfig.planar_ratio): F fitted to noisy seeds of a plane is degenerate (F = [e']x H for any
#: epipole e', which then catches outliers and off-H noise; benchmarks/results/planar_dev.md).
PLANAR_RATIO = 0.8
MIN_INLIERS = 15        # a trusted model explains at least this many seeds ...
MIN_INLIER_RATIO = 0.4  # ... making at least this share of them
#: OpenCV's USAC with local optimisation for F and E: ~5x faster than USAC_MAGSAC on our seeds
#: (0.7 vs 3.4 ms per essential matrix) and more inliers at the same threshold, so more view
#: pairs are trusted (benchmarks/results/stage_breakdown.md, geometric_eval.md).
EPIPOLAR_ESTIMATOR = cv2.USAC_ACCURATE
#: An essential matrix whose estimator inliers are less than this share in front of both
#: cameras is degenerate (seen on generated orbit scenes): USAC_MAGSAC is tried instead.
CHEIRAL_SHARE = 0.8


def check_planar_ratio(ratio: float, name: str = "planar_ratio") -> None:
    """Refuse an H-vs-F ratio (:data:`PLANAR_RATIO`) outside (0, 1]; ``name`` says whose."""
    if not 0.0 < ratio <= 1.0:
        raise ValueError(f"{name} must be in (0, 1], got {ratio}")


@numba.extending.register_jitable
def trusted_support(inliers: int, seeds: int, min_inliers: int = MIN_INLIERS,
                    min_inlier_ratio: float = MIN_INLIER_RATIO) -> bool:
    """Whether a model explaining ``inliers`` of ``seeds`` pairs may be believed: at least
    ``min_inliers`` of them, making at least ``min_inlier_ratio`` of the seeds."""
    return inliers >= min_inliers and inliers >= min_inlier_ratio * seeds


def may_be_trusted(xa: np.ndarray, xb: np.ndarray, px: float = RANSAC_PX, epipolar_px: float = EPIPOLAR_PX,
                   min_inliers: int = MIN_INLIERS, min_inlier_ratio: float = MIN_INLIER_RATIO,
                   seed: int = 0, max_iters: int = 2000) -> bool:
    """Whether a fit of these seed pairs (:func:`fit_pair`) could give a trusted model: the fits
    from pixels, H and F, as :func:`fit_pair` runs them, reach trusted support
    (:func:`trusted_support`). An essential matrix's inliers are a fundamental matrix's
    (F = K_b^-T E K_a^-1), so where no F reaches that support no E does either, up to RANSAC's
    chance; E's failure is the dear one (1 000 iterations, then USAC_MAGSAC again: ~27 ms on 120
    seeds that share no scene, against ~3 ms for H and F).

    Shapes: xa, xb (S, 2) pixels.
    """
    n = xa.shape[0]
    if n < MIN_SEEDS:
        return False
    a = np.ascontiguousarray(xa, np.float64)
    b = np.ascontiguousarray(xb, np.float64)
    H, nh = _fit_homography(a, b, px, seed, max_iters)
    if H is not None and trusted_support(nh, n, min_inliers, min_inlier_ratio):
        return True
    _, nf = _fit_fundamental(a, b, epipolar_px, seed, EPIPOLAR_ESTIMATOR, max_iters)
    return trusted_support(nf, n, min_inliers, min_inlier_ratio)


@dataclasses.dataclass
class PairModel:
    """H and/or F of one view pair and their support.

    Attributes:
        planar: the homography explains the seeds about as well as F (ORB-SLAM-style model
            selection); then only H is used for residuals and guidance.
        seeds: the pairs the models were fitted on; inliers_h, inliers_f: how many of them
            each model explains (0 without the model).
        essential: F comes from an essential matrix (both cameras calibrated).
        px: the inlier threshold H was fitted with; epipolar_px: the Sampson distance within
            which a pair agrees with F (see :data:`AGREE_SIGMAS`); :meth:`agrees`;
            epipolar_fit_px: the inlier threshold F was fitted with; noise_px: AGREE_SIGMAS x the
            keypoint noise estimated from F's inliers, unclipped (epipolar_px is it clipped to
            [AGREE_MIN_PX, epipolar_fit_px]; 0 without F).
    """

    H: Optional[np.ndarray]
    F: Optional[np.ndarray]
    planar: bool = False
    seeds: int = 0
    inliers_h: int = 0
    inliers_f: int = 0
    essential: bool = False
    px: float = RANSAC_PX
    epipolar_px: float = EPIPOLAR_PX
    epipolar_fit_px: float = EPIPOLAR_PX
    noise_px: float = 0.0

    @property
    def inliers(self) -> int:
        """Seeds explained by the selected model (H when planar, else F)."""
        return self.inliers_h if self.planar else self.inliers_f

    def trusted(self, min_inliers: int = MIN_INLIERS, min_inlier_ratio: float = MIN_INLIER_RATIO) -> bool:
        """Whether the selected model has the support to be believed (module docstring)."""
        return trusted_support(self.inliers, self.seeds, min_inliers, min_inlier_ratio)

    def selected(self) -> "PairModel":
        """This model with only the selected H or F kept."""
        keep_h, keep_f = (self.H, None) if self.planar else (None, self.F)
        return dataclasses.replace(self, H=keep_h, F=keep_f)

    @functools.cached_property
    def H_inverse(self) -> Optional[np.ndarray]:
        """H⁻¹ (3, 3), computed once per model (a window's checks transfer through it hundreds of
        times); None without H or where H is singular (no pair agrees with it then)."""
        if self.H is None:
            return None
        try:
            return np.linalg.inv(self.H)
        except np.linalg.LinAlgError:
            return None

    @property
    def inlier_share(self) -> float:
        """Share of the seeds the selected model explains."""
        return self.inliers / max(self.seeds, 1)

    def rechecked(self, xa: np.ndarray, xb: np.ndarray) -> "PairModel":
        """The selected model with its support counted on other seeds (its fit thresholds; no
        cheirality test): e.g. the next window's seeds of the same camera pair.

        Shapes: xa, xb (S, 2).
        """
        rh, rf = residuals(self.selected(), xa, xb)
        inliers = int((rh <= self.px).sum()) if self.planar else int((rf <= self.epipolar_fit_px).sum())
        support = {"inliers_h": inliers} if self.planar else {"inliers_f": inliers}
        return dataclasses.replace(self.selected(), seeds=int(xa.shape[0]), **support)

    def agrees(self, xa: np.ndarray, xb: np.ndarray, slack: float = 1.0) -> np.ndarray:
        """(M,) bool: each pair xa[m] <-> xb[m] is an inlier of the selected model: its residual
        within ``slack`` x the model's tolerance (``px`` for H, ``epipolar_px`` for F)."""
        return self.agreeing(*residuals(self.selected(), xa, xb), slack)

    def agreeing(self, res_h: np.ndarray, res_f: np.ndarray, slack: float = 1.0) -> np.ndarray:
        """:meth:`agrees` from the pairs' residuals (:func:`residuals`) under this model or its
        selected one: the rule reads only the selected model's residual.

        Shapes: res_h, res_f (M,) -> (M,) bool.
        """
        by_h, tolerance = self.inlier_rule
        return (res_h if by_h else res_f) <= slack * tolerance

    @property
    def inlier_rule(self) -> Tuple[bool, float]:
        """(whether :meth:`agrees` reads the H residual, else the F one; the tolerance it holds
        that residual to, before ``slack``)."""
        return (True, self.px) if self.planar else (False, self.epipolar_px)


def fit_pair(xa: np.ndarray, xb: np.ndarray, px: float = RANSAC_PX, seed: int = 0,
             K_a: Optional[np.ndarray] = None, K_b: Optional[np.ndarray] = None,
             epipolar_px: float = EPIPOLAR_PX, estimator: int = EPIPOLAR_ESTIMATOR,
             max_iters: int = 2000, fine_px: float = 0.0, planar_ratio: float = PLANAR_RATIO) -> Optional[PairModel]:
    """H and F (each None if it fails) from seed pairs xa[i] <-> xb[i] (pixels); None when
    neither fits. With both intrinsics K_a, K_b (3, 3) the epipolar model is an essential
    matrix (module docstring). ``px``, ``epipolar_px``: the inlier thresholds of H and F;
    ``fine_px``: F's threshold for keypoints localised to a fraction of a pixel, tried first
    with at most :data:`FINE_MAX_ITERS` iterations (module docstring; 0 or >= ``epipolar_px``:
    not tried); ``estimator``: OpenCV's method for F or E (MAGSAC follows it where an E is
    degenerate); ``max_iters``: RANSAC iterations of H and of F from pixels (fewer bound the
    cost and find only models of high inlier shares); ``planar_ratio``: the pair is planar (H
    selected) when H explains at least this share of the seeds F explains within ``epipolar_px``.

    Shapes: xa, xb (S, 2).
    """
    n = xa.shape[0]
    if n < MIN_SEEDS:
        return None
    a = np.ascontiguousarray(xa, np.float64)
    b = np.ascontiguousarray(xb, np.float64)
    H, nh = _fit_homography(a, b, px, seed, max_iters)
    calibrated = K_a is not None and K_b is not None

    def fit_epipolar(threshold: float, iters: Optional[int] = None) -> Tuple[Optional[np.ndarray], int]:
        """F (or E) at ``threshold``; ``iters``: RANSAC iterations (None: the path's usual count)."""
        if calibrated:
            return _fit_essential(a, b, threshold, K_a, K_b, seed, estimator,
                                  ESSENTIAL_MAX_ITERS if iters is None else iters)
        return _fit_fundamental(a, b, threshold, seed, estimator, max_iters if iters is None else iters)

    fine = False
    if 0.0 < fine_px < epipolar_px:
        F, nf = fit_epipolar(fine_px, FINE_MAX_ITERS)
        if F is not None and trusted_support(nf, n, MIN_INLIERS, FINE_MIN_INLIER_RATIO):
            res = sampson_distance(F, a, b)
            fine = bool((res <= fine_px).sum() >= FINE_SHARE * (res <= epipolar_px).sum())
    if not fine:
        F, nf = fit_epipolar(epipolar_px)
        res = sampson_distance(F, a, b) if F is not None else None
    if H is None and F is None:
        return None
    fit_px = fine_px if fine else epipolar_px
    # H against F on equal terms: the seeds F explains within epipolar_px, whatever it was fitted at
    nf_at_epipolar_px = int((res <= epipolar_px).sum()) if fine else nf
    planar = H is not None and (F is None or nh >= planar_ratio * nf_at_epipolar_px)
    if not planar and F is None:
        return None
    agree_px, noise_px = fit_px, 0.0
    if F is not None:
        inlier_res = res[res <= fit_px]
        noise_px = AGREE_SIGMAS * float(np.median(inlier_res)) / 0.674 if inlier_res.size else 0.0
        agree_px = float(np.clip(noise_px, min(AGREE_MIN_PX, fit_px), fit_px))
    return PairModel(H, F, planar, seeds=n, inliers_h=nh, inliers_f=nf, essential=calibrated and F is not None,
                     px=px, epipolar_px=agree_px, epipolar_fit_px=fit_px, noise_px=noise_px)


def _fit_homography(a: np.ndarray, b: np.ndarray, px: float, seed: int,
                    max_iters: int) -> Tuple[Optional[np.ndarray], int]:
    """H (None if it fails or is singular) and its inlier count (0 without H)."""
    cv2.setRNGSeed(seed)
    try:
        H, mh = cv2.findHomography(a, b, cv2.USAC_MAGSAC, px, maxIters=max_iters, confidence=0.999)
    except cv2.error:
        return None, 0
    if H is None or mh is None or int(mh.sum()) < 8 or abs(np.linalg.det(H)) < 1e-8:
        return None, 0
    return H, int(mh.sum())


def _fit_fundamental(a: np.ndarray, b: np.ndarray, px: float, seed: int,
                     estimator: int = EPIPOLAR_ESTIMATOR, max_iters: int = 2000) -> Tuple[Optional[np.ndarray], int]:
    cv2.setRNGSeed(seed)
    try:
        F, mf = cv2.findFundamentalMat(a, b, estimator, px, 0.999, max_iters)
    except cv2.error:
        return None, 0
    if F is None or F.shape != (3, 3) or mf is None or int(mf.sum()) < MIN_SEEDS:
        return None, 0
    return F, int(mf.sum())


def _fit_essential(a: np.ndarray, b: np.ndarray, px: float, K_a: np.ndarray, K_b: np.ndarray,
                   seed: int, estimator: int = EPIPOLAR_ESTIMATOR,
                   max_iters: int = ESSENTIAL_MAX_ITERS) -> Tuple[Optional[np.ndarray], int]:
    """F = K_b⁻ᵀ E K_a⁻¹ from the 5-point essential matrix of calibrated points; inliers are
    the seeds within ``px`` (pixels, via the mean focal length) that triangulate in front of
    both cameras."""
    ua, ub = unproject(K_a, a)[:, :2], unproject(K_b, b)[:, :2]
    focal = 0.25 * (K_a[0, 0] + K_a[1, 1] + K_b[0, 0] + K_b[1, 1])
    best, inliers = None, 0
    for method in (estimator, cv2.USAC_MAGSAC):
        E, count, fitted = _essential_with_cheirality(ua, ub, px / focal, method, seed, max_iters)
        if count > inliers:
            best, inliers = E, count
        # an E whose inliers mostly fail the cheirality test is degenerate: try MAGSAC's
        if count >= CHEIRAL_SHARE * fitted:
            break
    E = best
    if inliers < MIN_SEEDS:
        return None, 0
    F = np.linalg.inv(K_b).T @ E @ np.linalg.inv(K_a)
    return F / np.linalg.norm(F), inliers


def _essential_with_cheirality(ua: np.ndarray, ub: np.ndarray, threshold: float, method: int, seed: int,
                               max_iters: int = ESSENTIAL_MAX_ITERS) -> Tuple[Optional[np.ndarray], int, int]:
    """(E, inliers in front of both cameras, inliers of the estimator) on calibrated points; the
    5-point solver may return several solutions stacked (k·3, 3): the one with most in front."""
    cv2.setRNGSeed(seed)
    try:
        E_all, me = cv2.findEssentialMat(ua, ub, np.eye(3), method, 0.999, threshold, maxIters=max_iters)
        if E_all is None or me is None or E_all.ndim != 2 or E_all.shape[1] != 3 or E_all.shape[0] % 3:
            return None, 0, 0
        best, inliers = None, 0
        for E in np.split(E_all, E_all.shape[0] // 3):
            _, _, _, front = cv2.recoverPose(E, ua, ub, np.eye(3), mask=me.copy())
            count = int((front.ravel() > 0).sum())
            if count > inliers:
                best, inliers = E, count
    except cv2.error:
        return None, 0, 0
    return best, inliers, int(me.sum())


def residuals(model: Optional[PairModel], xa: np.ndarray, xb: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(H symmetric transfer error, F Sampson distance) in pixels; inf where a model is missing
    (both for no model, None; H's where it is singular).

    Shapes: xa, xb (M, 2) -> (M,) float64 twice.
    """
    return matrix_residuals(np.ascontiguousarray(xa, np.float64), np.ascontiguousarray(xb, np.float64),
                      *model_matrices(model))


def model_matrices(model: Optional[PairModel]):
    """``model`` as :func:`matrix_residuals` takes it: H, H⁻¹, F (3, 3) float64 each (zeros where
    missing), whether H is used (it is, with an inverse) and whether F is; None (no model):
    neither is used."""
    missing = np.zeros((3, 3))
    if model is None:
        return missing, missing, missing, False, False
    F, Hi = model.F, model.H_inverse
    H = None if Hi is None else model.H
    return (missing if H is None else np.asarray(H, np.float64), missing if Hi is None else Hi,
            missing if F is None else np.asarray(F, np.float64), H is not None, F is not None)


@numba.njit(cache=True, nogil=True)
def matrix_residuals(xa, xb, H, Hi, F, has_h, has_f):
    """:func:`residuals`' arithmetic, one pass over the pairs (a window asks for it hundreds of
    times, on a few dozen pairs each: numpy's per-call overhead was most of its cost). The
    formulas of :func:`gcn_match_ros.geometry.transfer` and
    :func:`gcn_match_ros.geometry.sampson_distance`, equal to them up to rounding (~1e-13 px)."""
    n = xa.shape[0]
    rh = np.full(n, np.inf)
    rf = np.full(n, np.inf)
    for m in range(n):
        x, y, u, v = xa[m, 0], xa[m, 1], xb[m, 0], xb[m, 1]
        if has_h:
            rh[m] = h_residual(x, y, u, v, H, Hi)
        if has_f:
            rf[m] = f_residual(x, y, u, v, F)
    return rh, rf


@numba.njit(cache=True, nogil=True, inline="always")
def h_residual(x, y, u, v, H, Hi):
    """One pair's (x, y) <-> (u, v) H residual of :func:`matrix_residuals`: the one owner of its
    arithmetic, for callers that look each pair's model up."""
    z = x * H[2, 0] + y * H[2, 1] + H[2, 2]
    z = z if abs(z) > 1e-12 else 1e-12
    zi = u * Hi[2, 0] + v * Hi[2, 1] + Hi[2, 2]
    zi = zi if abs(zi) > 1e-12 else 1e-12
    return transfer_error_px((x * H[0, 0] + y * H[0, 1] + H[0, 2]) / z,
                             (x * H[1, 0] + y * H[1, 1] + H[1, 2]) / z, u, v,
                             (u * Hi[0, 0] + v * Hi[0, 1] + Hi[0, 2]) / zi,
                             (u * Hi[1, 0] + v * Hi[1, 1] + Hi[1, 2]) / zi, x, y)


@numba.njit(cache=True, nogil=True, inline="always")
def f_residual(x, y, u, v, F):
    """One pair's (x, y) <-> (u, v) F residual (Sampson) of :func:`matrix_residuals`, as
    :func:`h_residual`."""
    return sampson_error_px(x * F[0, 0] + y * F[0, 1] + F[0, 2],    # F x_a: the line in b
                            x * F[1, 0] + y * F[1, 1] + F[1, 2],
                            x * F[2, 0] + y * F[2, 1] + F[2, 2],
                            u * F[0, 0] + v * F[1, 0] + F[2, 0],    # Fᵀ x_b: the line in a
                            u * F[0, 1] + v * F[1, 1] + F[2, 1], u, v)


@numba.njit(cache=True, nogil=True, inline="always")
def transfer_error_px(hx, hy, u, v, gx, gy, x, y):
    """The symmetric transfer error of a pair (x, y) <-> (u, v) under a homography H, given
    H (x, y) = (hx, hy) and H⁻¹ (u, v) = (gx, gy): the mean of the two distances, pixels. One
    owner of the formula for :func:`residuals` and the track check
    (:func:`gcn_match_ros.edges.consistency.TrackCheck`, which transfers each keypoint once)."""
    dx, dy, ex, ey = hx - u, hy - v, gx - x, gy - y
    return 0.5 * (np.sqrt(dx * dx + dy * dy) + np.sqrt(ex * ex + ey * ey))


@numba.njit(cache=True, nogil=True, inline="always")
def sampson_error_px(l0, l1, l2, m0, m1, u, v):
    """The Sampson distance of a pair x_a <-> x_b = (u, v) under F, given the line
    F x_a = (l0, l1, l2) in b and the first two entries (m0, m1) of Fᵀ x_b, pixels (as
    :func:`gcn_match_ros.geometry.sampson_distance`). One owner of the formula for
    :func:`residuals` and the track check."""
    return abs(u * l0 + v * l1 + l2) / max(np.sqrt(l0 * l0 + l1 * l1 + m0 * m0 + m1 * m1), 1e-12)
