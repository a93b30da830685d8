"""Pairs their own two-view model cannot tell apart from a neighbour: Lowe's ratio along the
epipolar line.

A repeated structure seen by cameras moving along it (a facade's windows, a fence) puts the
repetitions of a point on the same epipolar line: a match shifted by one repetition agrees
with the true geometry to within pixels, so no epipolar check can refuse it, and on the
held-out castle-P19 such pairs were most of gcn's geometrically wrong matches. Two views
cannot decide between the repetitions; what they can tell is that the choice is ambiguous.
A pair (a, b) of a view pair with a trusted epipolar model is *ambiguous* when another
keypoint within ``BAND_PX`` of its epipolar line — in view b along a's line, or in view a
along b's line — is nearly as similar to it as its partner::

    d(s_ab) >= ratio * d(s_runner_up),    d(s) = sqrt(2 - 2 s)  (descriptors.cosine_distance)

(a partner that is not even the best along the line has a ratio above 1). Planar models
(homographies) are left alone: they map a point to a point, so a repetition is not on the
same locus.

Measured (benchmarks/results/geometric_eval.md, ``gcn:epipolar_ratio=0.8``): geometric
precision castle-P19 0.80 -> 0.85 and development scenes 0.93 -> 0.95, at 1.5x / 1.7x
nn-ransac's consistent pairs (from 1.9x / 1.8x). It is an option, off by default: where
descriptors barely tell points apart, every right pair has a rival on its line — on the
generated small-object scenes (true-match cosine ~0.66, the rival's ~0.6, and the scene's
points crowd the epipolar lines) it drops most right pairs (3 x 80 points F1 0.88 -> 0.28).
"""
from __future__ import annotations

from typing import Dict, Tuple

import numba
import numpy as np

from ..descriptors import cosine_distance
from ..similarity import DescriptorSimilarity
from .verify import PairModel

__all__ = ["BAND_PX", "ambiguous_pairs", "band_runner_up"]

#: the band around an epipolar line in which another keypoint competes with a pair's partner:
#: about the 2 px a right match may lie off the true line plus a model's own error
BAND_PX = 3.0


@numba.njit(cache=True)
def _band_two_best(F, xa, xb, sim, transposed, band_px):
    """For each keypoint of view a (``transposed``: of view b), its two most similar keypoints
    of the other view within ``BAND_PX`` of its epipolar line: (n,) index of the best (-1:
    none), (n,) its cosine and (n,) the second's (-inf: none)."""
    n_from = xb.shape[0] if transposed else xa.shape[0]
    n_to = xa.shape[0] if transposed else xb.shape[0]
    best_at = np.full(n_from, -1, np.int64)
    best = np.full(n_from, -np.inf)
    second = np.full(n_from, -np.inf)
    for u in range(n_from):
        if transposed:  # the line of b's point in view a: F^T [x, y, 1]
            x, y = xb[u, 0], xb[u, 1]
            l0 = F[0, 0] * x + F[1, 0] * y + F[2, 0]
            l1 = F[0, 1] * x + F[1, 1] * y + F[2, 1]
            l2 = F[0, 2] * x + F[1, 2] * y + F[2, 2]
        else:           # the line of a's point in view b: F [x, y, 1]
            x, y = xa[u, 0], xa[u, 1]
            l0 = F[0, 0] * x + F[0, 1] * y + F[0, 2]
            l1 = F[1, 0] * x + F[1, 1] * y + F[1, 2]
            l2 = F[2, 0] * x + F[2, 1] * y + F[2, 2]
        reach = band_px * np.sqrt(l0 * l0 + l1 * l1)
        for k in range(n_to):
            xk, yk = (xa[k, 0], xa[k, 1]) if transposed else (xb[k, 0], xb[k, 1])
            if abs(l0 * xk + l1 * yk + l2) > reach:
                continue
            s = sim[k, u] if transposed else sim[u, k]
            if s > best[u]:
                second[u] = best[u]
                best[u], best_at[u] = s, k
            elif s > second[u]:
                second[u] = s
    return best_at, best, second


def band_runner_up(F: np.ndarray, xa: np.ndarray, xb: np.ndarray, sim: np.ndarray, ia: np.ndarray,
                   ib: np.ndarray, band_px: float = BAND_PX) -> np.ndarray:
    """The best cosine of any other keypoint near each pair's epipolar lines.

    Args:
        F: (3, 3) fundamental matrix of views a -> b (x_b^T F x_a = 0), pixels.
        xa, xb: (n_a, 2), (n_b, 2) keypoints of the two views.
        sim: (n_a, n_b) cosines between their descriptors.
        ia, ib: (M,) the pairs, indices into views a and b.

    Returns:
        (M,) float64: the largest cosine with the pair's other member of a keypoint k != ib[m]
        of view b within ``BAND_PX`` of F x_a, or k != ia[m] of view a within ``BAND_PX`` of
        F^T x_b; -inf where the bands hold no other keypoint. Each keypoint's band is scanned
        once (its two best), whatever the number of pairs.
    """
    F, xa, xb = np.asarray(F, np.float64), np.asarray(xa, np.float64), np.asarray(xb, np.float64)
    sim = np.ascontiguousarray(sim, np.float32)
    in_b_at, in_b, in_b_second = _band_two_best(F, xa, xb, sim, False, float(band_px))
    in_a_at, in_a, in_a_second = _band_two_best(F, xa, xb, sim, True, float(band_px))
    from_a = np.where(in_b_at[ia] == ib, in_b_second[ia], in_b[ia])   # other keypoints of b on a's line
    from_b = np.where(in_a_at[ib] == ia, in_a_second[ib], in_a[ib])   # other keypoints of a on b's line
    return np.maximum(from_a, from_b)


def ambiguous_pairs(models: Dict[Tuple[int, int], PairModel], similarity: DescriptorSimilarity, normalization: str,
                    view_offsets: np.ndarray, keypoints: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    ratio: float) -> np.ndarray:
    """Which pairs are ambiguous along their epipolar line (module docstring).

    Args:
        models: (a, b), a < b -> the view pair's trusted model (or None); pairs of other view
            pairs, and of planar models, are never ambiguous.
        similarity, normalization: the window's descriptor cosines, as the solver compares them.
        view_offsets: (V + 1,); keypoints: (N, 2).
        rows, cols: (M,) global keypoint indices, view of rows < view of cols.
        ratio: the ratio at and above which a pair is ambiguous (> 1: only partners that another
            keypoint on the line beats by that much).

    Returns:
        (M,) bool.
    """
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    out = np.zeros(rows.shape[0], bool)
    if not rows.size:
        return out
    offsets = np.asarray(view_offsets, np.int64)
    view_a = np.searchsorted(offsets, rows, side="right") - 1
    view_b = np.searchsorted(offsets, cols, side="right") - 1
    xy = np.asarray(keypoints, np.float64)
    for (a, b), model in models.items():
        if model is None or model.F is None or model.planar:
            continue
        sel = np.flatnonzero((view_a == a) & (view_b == b))
        if not sel.size:
            continue
        ia, ib = rows[sel] - offsets[a], cols[sel] - offsets[b]
        sim = similarity.block(a, b, normalization).numpy()
        runner_up = band_runner_up(model.F, xy[offsets[a]:offsets[a + 1]], xy[offsets[b]:offsets[b + 1]], sim, ia, ib)
        own = cosine_distance(sim[ia, ib].astype(np.float64))
        out[sel] = np.isfinite(runner_up) & (own >= ratio * cosine_distance(runner_up))
    return out
