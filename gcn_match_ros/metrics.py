"""Scores of a matcher's result against ground truth (shared/spec/problem-format.md, Scoring).

Everything is counted over unordered pairs of keypoints in *different* views whose
labels are known (``gt_track != -2``); a pair is true when both keypoints have the same
``gt_track >= 0``. Nothing here forms an N×N matrix: pair counts come from group sizes.

- precision / recall / F1 of the hard tracks,
- average precision of the soft pair scores (unlisted pairs score 0),
- mean similarity of same-point and of different-point pairs (diagonal excluded),
- the paper's L1/L2, mean |S − XXᵀ| over all N_lab² entries with S = I + scores — kept only
  for comparison with its table: predicting the identity beats most methods on it
  (shared/notes/evaluation.md), so :func:`reference_rows` gives the identity and all-zero rows.
"""
from __future__ import annotations

from typing import Dict, Sequence, Tuple

import numpy as np

from .problem import Problem, Result
from .rounding import tracks_to_pairs

__all__ = ["score_result", "average_precision", "pr_curve", "scored_pairs", "reference_rows", "count_pairs", "mean_scores",
           "paired_bootstrap", "SCORE_KEYS"]

SCORE_KEYS = ("P", "R", "F1", "AP", "same_sim", "diff_sim", "L1", "L2", "seconds")


def count_pairs(labels: np.ndarray, view_index: np.ndarray):
    """Number of cross-view pairs among ``labels != -2`` and of true (same label >= 0) pairs.

    Returns:
        (labelled_pairs, true_pairs) as Python ints.
    """
    lab = labels != -2
    n = int(lab.sum())
    per_view = np.bincount(view_index[lab], minlength=int(view_index.max(initial=-1)) + 1)
    labelled = n * (n - 1) // 2 - int((per_view * (per_view - 1) // 2).sum())
    pos = labels >= 0
    if not pos.any():
        return labelled, 0
    # Pairs within each gt group, minus those whose two keypoints lie in one view.
    _, group_sizes = np.unique(labels[pos], return_counts=True)
    _, gv_sizes = np.unique(labels[pos] * (int(view_index.max()) + 1) + view_index[pos],
                            return_counts=True)
    true = int((group_sizes * (group_sizes - 1) // 2).sum() - (gv_sizes * (gv_sizes - 1) // 2).sum())
    return labelled, true


def _pair_truth(gt: np.ndarray, view_index: np.ndarray, rows: np.ndarray, cols: np.ndarray):
    """For listed pairs: mask of pairs that are scored (both labelled, different views) and truth."""
    scored = (gt[rows] != -2) & (gt[cols] != -2) & (view_index[rows] != view_index[cols])
    truth = (gt[rows] == gt[cols]) & (gt[rows] >= 0)
    return scored, truth


def pr_curve(scores: np.ndarray, truth: np.ndarray, n_true: int, n_pairs: int):
    """Precision and recall at every distinct score threshold, highest first; pairs not listed
    score 0 (so the last point has recall 1 when n_true > 0).

    Args:
        scores, truth: (M,) listed pairs' scores and whether each is true.
        n_true: true pairs in total (listed or not); n_pairs: labelled pairs in total.
    Returns:
        (precision, recall, thresholds), each (T,).
    """
    listed_true = int(truth.sum())
    s = np.concatenate([np.asarray(scores, np.float64), [0.0]])
    tp_w = np.concatenate([truth.astype(np.float64), [n_true - listed_true]])
    fp_w = np.concatenate([(~truth).astype(np.float64), [n_pairs - n_true - (truth.size - listed_true)]])
    order = np.argsort(-s, kind="stable")
    s, tp_w, fp_w = s[order], tp_w[order], fp_w[order]
    last_of_group = np.r_[s[1:] != s[:-1], True]  # ties form one threshold
    tp = np.cumsum(tp_w)[last_of_group]
    fp = np.cumsum(fp_w)[last_of_group]
    precision = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1e-300), 1.0)
    recall = tp / max(n_true, 1)
    return precision, recall, s[last_of_group]


def average_precision(scores: np.ndarray, truth: np.ndarray, n_true: int, n_pairs: int) -> float:
    """Area under the precision–recall curve, pairs not listed scoring 0.

    AP = Σ_k (R_k − R_{k−1}) P_k over distinct score thresholds (ties form one step), as
    scikit-learn's ``average_precision_score`` on the full pair list would give.
    """
    if n_true == 0:
        return float("nan")
    precision, recall, _ = pr_curve(scores, truth, n_true, n_pairs)
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def scored_pairs(problem: Problem, result: Result):
    """The result's listed pairs that are scored: (scores, truth, n_true, n_pairs)."""
    view = problem.view_index
    n_pairs, n_true = count_pairs(problem.gt_track, view)
    scored, truth = _pair_truth(problem.gt_track, view, result.pair_rows, result.pair_cols)
    return result.pair_scores[scored].astype(np.float64), truth[scored], n_true, n_pairs


def score_result(problem: Problem, result: Result) -> Dict[str, float]:
    """All scores of one result. Requires ``problem.gt_track``."""
    if problem.gt_track is None:
        raise ValueError(f"problem '{problem.name}' has no gt_track: cannot score")
    result.validate_against(problem)
    gt = problem.gt_track
    view = problem.view_index
    n_pairs, n_true = count_pairs(gt, view)

    pr, pc = tracks_to_pairs(result.track)
    scored, truth = _pair_truth(gt, view, pr, pc)
    n_pred = int(scored.sum())
    tp = int((truth & scored).sum())
    precision = tp / n_pred if n_pred else 0.0
    recall = tp / n_true if n_true else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0

    s, t, _, _ = scored_pairs(problem, result)
    ap = average_precision(s, t, n_true, n_pairs)
    same = float(s[t].sum() / n_true) if n_true else float("nan")
    n_false = n_pairs - n_true
    diff = float(s[~t].sum() / n_false) if n_false else float("nan")
    l1, l2 = _paper_l1_l2(s, t, n_true, int((gt != -2).sum()))
    return {"P": precision, "R": recall, "F1": f1, "AP": ap, "same_sim": same, "diff_sim": diff,
            "L1": l1, "L2": l2, "seconds": result.seconds, "true_pairs": n_true}


def _paper_l1_l2(s: np.ndarray, t: np.ndarray, n_true: int, n_lab: int, diagonal: float = 1.0):
    """mean |S − XXᵀ| and mean (S − XXᵀ)² over the N_lab² entries; S symmetric with the listed
    cross-view scores, ``diagonal`` on its diagonal and 0 elsewhere."""
    if n_lab == 0:
        return float("nan"), float("nan")
    err = np.abs(s - t)
    missed = n_true - int(t.sum())  # true pairs not listed: |0 − 1| each
    diag = n_lab * abs(diagonal - 1.0)
    l1 = (2 * (err.sum() + missed) + diag) / n_lab ** 2
    l2 = (2 * ((err ** 2).sum() + missed) + diag) / n_lab ** 2
    return float(l1), float(l2)


def reference_rows(problem: Problem) -> Dict[str, Dict[str, float]]:
    """Scores of the trivial answers: the identity (nothing matched, S = I) and all zeros (S = 0)."""
    n = problem.n_keypoints
    empty = Result(track=np.full(n, -1), pair_rows=np.zeros(0), pair_cols=np.zeros(0),
                   pair_scores=np.zeros(0), method="identity")
    identity = score_result(problem, empty)
    zero = dict(identity)
    _, n_true = count_pairs(problem.gt_track, problem.view_index)
    zero["L1"], zero["L2"] = _paper_l1_l2(np.zeros(0), np.zeros(0, bool), n_true,
                                          int((problem.gt_track != -2).sum()), diagonal=0.0)
    return {"identity": identity, "all-zero": zero}


def mean_scores(rows) -> Dict[str, float]:
    """Mean of every score over problems; ``seconds`` is the median (spec: median runtime)."""
    out = {}
    for key in SCORE_KEYS:
        vals = np.array([r[key] for r in rows if key in r], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        if vals.size:
            out[key] = float(np.median(vals) if key == "seconds" else vals.mean())
    return out


def paired_bootstrap(a: Sequence[float], b: Sequence[float], resamples: int = 2000, level: float = 0.95,
                     seed: int = 0) -> Tuple[float, float, float]:
    """Mean of the paired differences ``a - b`` (one score per problem, two methods) and its
    percentile bootstrap confidence interval, resampling problems with replacement.

    Returns:
        (mean difference, lower, upper).
    """
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 1 or a.shape != b.shape or not a.size:
        raise ValueError(f"need two equally long, non-empty score lists, got shapes {a.shape} and {b.shape}")
    d = a - b
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, size=(resamples, d.size))].mean(axis=1)
    tail = (1 - level) / 2 * 100
    lo, hi = np.percentile(means, [tail, 100 - tail])
    return float(d.mean()), float(lo), float(hi)
