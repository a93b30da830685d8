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

Only pairs whose own cosine is at least :data:`MIN_JUDGED_COSINE` are judged. A repetition
is a near-copy: the pair and its rival are both very similar. Where descriptors barely tell
points apart, every right pair has a rival on its line — on the generated small-object scenes
(true-match cosine ~0.66, the rival's ~0.6, the scene's points crowding the epipolar lines)
judging every pair at 0.9 took F1 0.85 -> 0.56 (rome16k, 3 views); judged from 0.8 nothing
there changes, and castle-P19 keeps the gain (geometric precision 0.897 judging every pair,
0.896 from 0.8: benchmarks/results/geometric_eval.md).
"""
from __future__ import annotations

import numba
import numpy as np

from ..descriptors import cosine_distance
from ..similarity import DescriptorSimilarity
from ..view_pairs import by_view_pair
from .consistency import WindowGeometry

__all__ = ["BAND_PX", "MIN_JUDGED_COSINE", "ambiguous_pairs", "band_runner_up", "check_ratio", "near_copies"]

#: the band around an epipolar line in which another keypoint competes with a pair's partner:
#: about the 2 px a right match may lie off the true line plus a model's own error
BAND_PX = 3.0
#: pairs less similar than this (cosine) are not judged (module docstring): not near-copies,
#: so not repetitions (also the pairs :mod:`.neighbourhood`'s rule judges, :func:`near_copies`)
MIN_JUDGED_COSINE = 0.8


def check_ratio(ratio: float) -> None:
    """Refuse a solver's ``epipolar_ratio`` setting below 0 (0: the rule is off)."""
    if not ratio >= 0.0:
        raise ValueError(f"epipolar_ratio must be >= 0 (0: off), got {ratio}")


@numba.njit(cache=True, nogil=True)
def _band_two_best(F, x_from, x_to, sim, band_px, which):
    """For keypoints ``which`` of one view, their two most similar keypoints of the other view
    within ``band_px`` of their epipolar line F [x, y, 1]. ``sim`` may be the transpose of a
    C-contiguous block (it reads a few entries a row: copying the block cost more than the scan).

    Shapes: F (3, 3); x_from (n, 2); x_to (m, 2); sim (n, m); which (w,) -> (w,) index of the
    best (-1: none), (w,) its cosine and (w,) the second's (-inf: none).
    """
    n = which.shape[0]
    best_at = np.full(n, -1, np.int64)
    best = np.full(n, -np.inf)
    second = np.full(n, -np.inf)
    for t in range(n):
        u = which[t]
        x, y = x_from[u, 0], x_from[u, 1]
        l0 = F[0, 0] * x + F[0, 1] * y + F[0, 2]
        l1 = F[1, 0] * x + F[1, 1] * y + F[1, 2]
        l2 = F[2, 0] * x + F[2, 1] * y + F[2, 2]
        reach = band_px * np.sqrt(l0 * l0 + l1 * l1)
        for k in range(x_to.shape[0]):
            if abs(l0 * x_to[k, 0] + l1 * x_to[k, 1] + l2) > reach:
                continue
            s = sim[u, k]
            if s > best[t]:
                second[t] = best[t]
                best[t], best_at[t] = s, k
            elif s > second[t]:
                second[t] = s
    return best_at, best, second


def band_runner_up(F: np.ndarray, xa: np.ndarray, xb: np.ndarray, sim: np.ndarray, ia: np.ndarray,
                   ib: np.ndarray, band_px: float = BAND_PX) -> np.ndarray:
    """The best cosine of any other keypoint near each pair's epipolar lines.

    Args:
        F: (3, 3) fundamental matrix of views a -> b (x_b^T F x_a = 0), pixels.
        xa, xb: (n_a, 2), (n_b, 2) keypoints of the two views.
        sim: (n_a, n_b) cosines between their descriptors.
        ia, ib: (M,) the pairs, indices into views a and b.
        band_px: the band's half width around a line.

    Returns:
        (M,) float64: the largest cosine with the pair's other member of a keypoint k != ib[m]
        of view b within ``band_px`` of F x_a, or k != ia[m] of view a within ``band_px`` of
        F^T x_b; -inf where the bands hold no other keypoint. The band of each keypoint of a
        pair is scanned once (its two best), whatever the number of pairs it is in.
    """
    F, xa, xb = np.asarray(F, np.float64), np.asarray(xa, np.float64), np.asarray(xb, np.float64)
    sim = np.asarray(sim, np.float32)
    ia, ib = np.asarray(ia, np.int64), np.asarray(ib, np.int64)
    scan_a, at_a = np.unique(ia, return_inverse=True)
    scan_b, at_b = np.unique(ib, return_inverse=True)
    in_b_at, in_b, in_b_second = _band_two_best(F, xa, xb, sim, float(band_px), scan_a)
    in_a_at, in_a, in_a_second = _band_two_best(np.ascontiguousarray(F.T), xb, xa, sim.T, float(band_px), scan_b)
    # other keypoints of b on a's line, other keypoints of a on b's line
    from_a = np.where(in_b_at[at_a] == ib, in_b_second[at_a], in_b[at_a])
    from_b = np.where(in_a_at[at_b] == ia, in_a_second[at_b], in_a[at_b])
    return np.maximum(from_a, from_b)


def ambiguous_pairs(geometry: WindowGeometry, similarity: DescriptorSimilarity, normalization: str,
                    rows: np.ndarray, cols: np.ndarray, ratio: float) -> np.ndarray:
    """Which pairs are ambiguous along their epipolar line (module docstring).

    Args:
        geometry: the window's trusted models; pairs of other view pairs, of planar models,
            and pairs less similar than :data:`MIN_JUDGED_COSINE` are never ambiguous.
        similarity, normalization: the window's descriptor cosines, as the solver compares them.
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
    offsets = geometry.problem.view_offsets
    view_a, view_b = geometry.view_index[rows], geometry.view_index[cols]
    xy = geometry.keypoints
    groups = by_view_pair(view_a, view_b)
    for (a, b), model in geometry.models.items():
        sel = groups.get((a, b))
        if model.F is None or model.planar or sel is None:
            continue
        ia, ib = rows[sel] - offsets[a], cols[sel] - offsets[b]
        sim = similarity.block(a, b, normalization).numpy()
        own_cosine = sim[ia, ib]
        judged = own_cosine >= MIN_JUDGED_COSINE
        if not judged.any():
            continue
        sel, ia, ib = sel[judged], ia[judged], ib[judged]
        runner_up = band_runner_up(model.F, xy[offsets[a]:offsets[a + 1]], xy[offsets[b]:offsets[b + 1]], sim, ia, ib)
        own = cosine_distance(own_cosine[judged].astype(np.float64))
        out[sel] = np.isfinite(runner_up) & (own >= ratio * cosine_distance(runner_up))
    return out


def near_copies(geometry: WindowGeometry, similarity: DescriptorSimilarity, normalization: str,
                rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Which pairs are similar enough to be a repetition of each other's point: cosine at least
    :data:`MIN_JUDGED_COSINE` (the pairs the rules against repetitions judge), in any view pair.

    Shapes: rows, cols (M,) global keypoint indices of different views -> (M,) bool.
    """
    lo, hi, va, vb = geometry.in_view_order(rows, cols)
    out = np.zeros(lo.shape[0], bool)
    offsets = geometry.problem.view_offsets
    for (a, b), sel in by_view_pair(va, vb).items():
        sim = similarity.block(a, b, normalization).numpy()
        out[sel] = sim[lo[sel] - offsets[a], hi[sel] - offsets[b]] >= MIN_JUDGED_COSINE
    return out
