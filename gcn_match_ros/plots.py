"""Figures (matplotlib, Agg backend: no display needed); nothing here computes results.

- :func:`plot_history`: training (thin) and validation (thick, dots) losses of one or
  several runs over steps, one panel per loss term; overlaying runs compares settings,
  e.g. with and without the geometric (epipolar) loss. :func:`gcn_match_ros.learn.train.train`
  writes ``curves.png`` with it.
- :func:`plot_pr_curves`: precision–recall curves of an :func:`gcn_match_ros.evaluation.evaluate`
  report.
- :func:`plot_reliability`: reliability diagram of soft scores — among pairs scored >= s,
  the share that is right (e.g. geometrically consistent) against s; on or above the
  diagonal a consumer can read a score as a lower bound of precision.
- :func:`plot_landmark_map`: a map of persistent landmarks seen from above (the two world
  axes the cameras move in most), the camera path, and how many windows each landmark lived.
- :func:`plot_similarity`: for one (small) problem with ground truth, the input graph A,
  the network's EEᵀ and the ground truth XXᵀ side by side, views in blocks and the
  keypoints of each view ordered by ground-truth track (so true matches form diagonals).
- :func:`plot_similarity_histograms`: distributions of EEᵀ over cross-view pairs of the
  same scene point and of different points (the paper's histograms).

``gcn-match plot`` draws them for training runs.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, Mapping, Optional, Sequence, Tuple, Union

import numpy as np

from .graph import CorrespondenceGraph
from .problem import Problem

__all__ = ["load_history", "plot_history", "plot_pr_curves", "plot_reliability", "plot_labels_against_geometry",
           "plot_landmark_map", "plot_similarity", "similarity_order", "cross_view_similarities",
           "plot_similarity_histograms"]

RunLike = Union[str, Path, Mapping[str, Any]]
_TERMS = ("loss", "recon", "epipolar", "edge")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path, dpi: int = 110) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    _plt().close(fig)
    return path


# ---------------------------------------------------------------------------
# Training curves
# ---------------------------------------------------------------------------
def load_history(run: RunLike) -> Dict[str, Any]:
    """A history dict from a run folder, a ``history.json`` path, or the dict itself.

    Raises:
        OSError: no history.json; ValueError: not a history.
    """
    if isinstance(run, Mapping):
        hist = dict(run)
    else:
        p = Path(run)
        if p.is_dir():
            p = p / "history.json"
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such history file (is {Path(run)} a training run folder?)")
        try:
            hist = json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{p}: not a JSON history ({exc})") from None
    if not isinstance(hist, dict) or not isinstance(hist.get("train", []), list):
        raise ValueError(f"{run}: not a training history (expected keys 'train', 'val')")
    hist.setdefault("train", [])
    hist.setdefault("val", [])
    return hist


def _series(entries: Sequence[Mapping[str, Any]], key: str) -> Tuple[np.ndarray, np.ndarray]:
    pts = [(e["step"], e[key]) for e in entries
           if key in e and e[key] is not None and math.isfinite(float(e[key]))]
    if not pts:
        return np.zeros(0), np.zeros(0)
    a = np.asarray(pts, dtype=np.float64)
    return a[:, 0], a[:, 1]


def _smooth(y: np.ndarray, n: int) -> np.ndarray:
    if n <= 1 or y.size < 2 * n:
        return y
    k = np.ones(n) / n
    pad = np.r_[np.full(n // 2, y[0]), y, np.full(n - 1 - n // 2, y[-1])]
    return np.convolve(pad, k, mode="valid")


def plot_history(runs: Union[RunLike, Sequence[RunLike]], path, labels: Optional[Sequence[str]] = None,
                 terms: Sequence[str] = _TERMS, log_y: Optional[bool] = None, title: str = "") -> Path:
    """Training and validation curves of one or several runs, one panel per loss term.

    Args:
        runs: run folders, ``history.json`` files or history dicts.
        labels: legend names (default: the folder names, else ``run 1``, ...).
        terms: loss keys to draw when present (``loss``, ``recon``, ``epipolar``, ``edge``).
        log_y: logarithmic loss axis; None = when a panel spans more than a factor 20.

    Returns:
        ``path`` (PNG). Training entries are thin lines (lightly smoothed when long),
        validation entries thick lines with dots, the best checkpoint a star.
    """
    if isinstance(runs, (str, Path, Mapping)):
        runs = [runs]
    hists = [load_history(r) for r in runs]
    if labels is None:
        labels = [Path(r).name if not isinstance(r, Mapping) else f"run {i + 1}" for i, r in enumerate(runs)]
    if len(labels) != len(hists):
        raise ValueError(f"{len(labels)} labels for {len(hists)} runs")
    present = [t for t in terms if any(_series(h["train"], t)[0].size or _series(h["val"], t)[0].size
                                       for h in hists)]
    if not present:
        raise ValueError("the histories hold no loss values to plot")
    plt = _plt()
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(1, len(present), figsize=(4.6 * len(present), 3.8), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    names = {"loss": "total loss", "recon": "reconstruction loss", "epipolar": "epipolar loss",
             "edge": "edge-head loss"}
    for ax, term in zip(axes[0], present):
        lo, hi = np.inf, -np.inf
        for i, (h, lab) in enumerate(zip(hists, labels)):
            c = colors[i % len(colors)]
            xs, ys = _series(h["train"], term)
            if xs.size:
                ax.plot(xs, _smooth(ys, max(1, xs.size // 50)), color=c, lw=1.0, alpha=0.55,
                        label=f"{lab} train")
                lo, hi = min(lo, ys.min()), max(hi, ys.max())
            xv, yv = _series(h["val"], term)
            if xv.size:
                ax.plot(xv, yv, color=c, lw=2.2, marker="o", ms=3.5, label=f"{lab} val")
                lo, hi = min(lo, yv.min()), max(hi, yv.max())
            best = h.get("best") or {}
            if term == "loss" and best.get("source") == "val" and best.get("step") is not None:
                ax.plot([best["step"]], [best["loss"]], marker="*", ms=13, color=c, mec="k", mew=0.6, ls="",
                        label=f"{lab} best (step {best['step']})")
        use_log = log_y if log_y is not None else (lo > 0 and hi / max(lo, 1e-12) > 20)
        if use_log:
            ax.set_yscale("log")
        ax.set_title(names.get(term, term))
        ax.set_xlabel("step")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
    handles, labs = axes[0][0].get_legend_handles_labels()
    axes[0][0].legend(handles, labs, fontsize=7, loc="best")
    fig.suptitle(title or "training (thin) and validation (thick) losses", fontsize=11)
    fig.tight_layout()
    return _save(fig, path)


# ---------------------------------------------------------------------------
# Precision-recall
# ---------------------------------------------------------------------------
def plot_pr_curves(report: Mapping[str, Any], path) -> Path:
    """Precision–recall curves of every method (pooled over problems) to a PNG."""
    fig, ax = _plt().subplots(figsize=(6, 5))
    for spec, entry in report["methods"].items():
        pr = entry.get("pr")
        if not pr or not pr["precision"]:
            continue
        ap = entry["mean"].get("AP", float("nan"))
        ax.plot(pr["recall"], pr["precision"], label=f"{entry['describe']} (AP {ap:.3f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title(f"Precision–recall over {len(report['problems'])} problems")
    fig.tight_layout()
    return _save(fig, path, dpi=120)


def plot_reliability(thresholds: Sequence[float], shares: Mapping[str, Sequence[float]], path,
                     counts: Optional[Mapping[str, Sequence[int]]] = None, title: str = "") -> Path:
    """Reliability diagram to a PNG: for each method, the right share among pairs scored >= s
    against s, with the diagonal (share = s) a calibrated score reaches.

    Args:
        thresholds: (T,) score thresholds s.
        shares: method -> (T,) right share among pairs scored >= s (NaN where none).
        counts: method -> (T,) number of those pairs, drawn as a second panel when given.
    """
    plt = _plt()
    fig, axes = plt.subplots(1, 2 if counts else 1, figsize=(10 if counts else 5.5, 4.5), squeeze=False)
    ax = axes[0, 0]
    s = np.asarray(thresholds, float)
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="share = s")
    for name, y in shares.items():
        ax.plot(s, np.asarray(y, float), marker="o", label=name)
    ax.set_xlabel("score threshold s")
    ax.set_ylabel("right share of pairs scored >= s")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    if counts:
        axc = axes[0, 1]
        for name, c in counts.items():
            axc.plot(s, np.asarray(c, float), marker="o", label=name)
        axc.set_xlabel("score threshold s")
        axc.set_ylabel("pairs scored >= s")
        axc.grid(alpha=0.3)
        axc.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, dpi=120)


def plot_labels_against_geometry(points: Mapping[str, Tuple[float, float]], path, title: str = "") -> Path:
    """Each method's F1 on the labels against its geometric precision on every predicted pair, to
    a PNG: where labels score only some of the pairs (pose scenes), a method can gain label F1 with
    pairs the true cameras call impossible, and the two scores together show it.

    Args:
        points: method -> (geometric precision, label F1), both in [0, 1] (NaN: not drawn).
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 5))
    for name, (x, y) in points.items():
        if np.isfinite(x) and np.isfinite(y):
            ax.scatter([x], [y], s=45, label=name)  # a legend, not labels: near points' names would overlap
    ax.set_xlabel("geometric precision (every predicted pair, true cameras)")
    ax.set_ylabel("F1 on the labels")
    ax.set_xlim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return _save(fig, path, dpi=120)


def plot_stage_times(windows: Mapping[str, Mapping[str, Mapping[str, float]]], path, title: str = "",
                     wall: Optional[Mapping[str, Mapping[str, float]]] = None) -> Path:
    """Where each window's time goes, to a PNG: one panel per window size (its own linear
    scale), one horizontal bar per solver, split into its stages.

    Args:
        windows: window label (e.g. "4 x 500") -> bar label (e.g. "gcn (stream)") -> stage ->
            milliseconds, stages in drawing order (the same names in every bar).
        wall: the same labels -> the solve's wall time, milliseconds, written at each bar
            (with its stages' sum where work on two threads made that larger); None: the sum.
    """
    plt = _plt()
    n_bars = max(len(bars) for bars in windows.values())
    height = (0.4 * n_bars + 0.9) * len(windows) + 1.0
    fig, axes = plt.subplots(len(windows), 1, figsize=(9, height), squeeze=False)
    colors = {}
    for ax, (window, bars) in zip(axes[:, 0], windows.items()):
        y = np.arange(len(bars))[::-1]
        left = np.zeros(len(bars))
        stage_names = list(next(iter(bars.values())))
        for name in stage_names:
            ms = np.array([bar.get(name, 0.0) for bar in bars.values()], float)
            bars_drawn = ax.barh(y, ms, left=left, height=0.7, color=colors.get(name),
                                 label=name if name not in colors else None)
            colors.setdefault(name, bars_drawn.patches[0].get_facecolor())
            left += ms
        walls = [None if wall is None else wall[window][label] for label in bars]
        for yi, total, wall_ms in zip(y, left, walls):
            text = f" {total:.0f} ms" if wall_ms is None or total <= 1.05 * wall_ms else \
                f" {wall_ms:.0f} ms wall ({total:.0f} ms on two threads)"
            ax.text(total, yi, text, va="center", fontsize=8)
        ax.set_yticks(y)
        ax.set_yticklabels(list(bars), fontsize=8)
        ax.set_xlim(0, (1.15 if wall is None else 1.5) * left.max())
        ax.set_title(window, fontsize=9, loc="left")
        ax.grid(alpha=0.3, axis="x")
    axes[-1, 0].set_xlabel("milliseconds per window (stages stacked)")
    if title:
        fig.suptitle(title, fontsize=10, y=1 - 0.1 / height, va="top")
    fig.legend(fontsize=7, ncol=9, loc="upper center", bbox_to_anchor=(0.5, 1 - 0.4 / height))
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.8 / height))
    return _save(fig, path, dpi=120)


def plot_landmark_map(points: np.ndarray, lifetimes: np.ndarray, camera_centers: np.ndarray, path,
                      title: str = "") -> Path:
    """Landmarks and the camera path from above, and the landmarks' lifetimes, to a PNG.

    Args:
        points: (M, 3) world points of the mapped landmarks; lifetimes: (M,) windows each lived.
        camera_centers: (C, 3) camera centres in window order (drawn as the path).
    The view is the plane of the two principal axes of the camera path and the points (the
    scene's "ground" for a rig moving over it).
    """
    plt = _plt()
    allp = np.vstack([np.asarray(points, float).reshape(-1, 3), np.asarray(camera_centers, float).reshape(-1, 3)])
    centre = allp.mean(0)
    axes2 = np.linalg.svd(allp - centre, full_matrices=False)[2][:2] if allp.shape[0] >= 2 else np.eye(3)[:2]
    p2 = (np.asarray(points, float).reshape(-1, 3) - centre) @ axes2.T
    c2 = (np.asarray(camera_centers, float).reshape(-1, 3) - centre) @ axes2.T
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(11, 4.8), gridspec_kw={"width_ratios": [2, 1]})
    sc = ax.scatter(p2[:, 0], p2[:, 1], c=lifetimes, s=4, cmap="viridis")
    ax.plot(c2[:, 0], c2[:, 1], "r.-", lw=1, ms=5, label="cameras (window order)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8, loc="best")
    fig.colorbar(sc, ax=ax, label="windows the landmark lived")
    ax.set_title(f"{len(p2)} mapped landmarks, seen from above", fontsize=9)
    lt = np.asarray(lifetimes, int)
    axh.hist(lt, bins=np.arange(0.5, max(lt.max(initial=1), 1) + 1.5), color="tab:blue")
    axh.set_xlabel("windows a landmark lived")
    axh.set_ylabel("landmarks")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path, dpi=110)


# ---------------------------------------------------------------------------
# Similarity matrices
# ---------------------------------------------------------------------------
def similarity_order(problem: Problem, max_per_view: int = 60) -> Tuple[np.ndarray, np.ndarray]:
    """Keypoints to show and the view boundaries of the figure.

    Per view: keypoints of ground-truth tracks sorted by track id (tracks seen in the most
    views first when there are more than ``max_per_view``), then a few unmatched (-1) and
    unlabelled (-2) ones. Returns ``(rows into the problem (M,), offsets (V+1,))``.
    """
    gt = problem.gt_track
    if gt is None:
        raise ValueError(f"problem '{problem.name}' has no gt_track: cannot order by track")
    vi = problem.view_index
    ids = np.unique(gt[gt >= 0])
    if ids.size:
        n_views = np.array([np.unique(vi[gt == i]).size for i in ids])
        shared = ids[n_views >= 2]
        rank = np.lexsort((shared, -n_views[n_views >= 2]))
        keep_ids = np.sort(shared[rank[:max_per_view]])
    else:
        keep_ids = np.zeros(0, np.int64)
    rows, offsets = [], [0]
    n_extra = max(2, max_per_view // 6)
    for v in range(problem.n_views):
        idx = np.arange(*problem.view_offsets[v:v + 2])
        g = gt[idx]
        tracked = idx[np.isin(g, keep_ids)]
        tracked = tracked[np.argsort(gt[tracked], kind="stable")][:max_per_view]
        room = max(0, min(n_extra, max_per_view - tracked.size))
        others = np.r_[idx[g == -1], idx[g == -2], idx[(g >= 0) & ~np.isin(g, keep_ids)]][:room]
        sel = np.r_[tracked, others].astype(np.int64)
        rows.append(sel)
        offsets.append(offsets[-1] + sel.size)
    return np.concatenate(rows), np.asarray(offsets)


def plot_similarity(problem: Problem, embeddings: np.ndarray, graph: CorrespondenceGraph, path,
                    max_per_view: int = 60, title: str = "") -> Path:
    """Input graph A, output EEᵀ and ground truth XXᵀ of one problem, blockwise by view,
    keypoints ordered by ground-truth track (:func:`similarity_order`; larger problems show
    a subset).

    Shapes: embeddings E (N, d) of the whole problem (e.g. :func:`gcn_match_ros.learn.model.embed_problem`),
    graph its input graph over the N keypoints."""
    rows, offsets = similarity_order(problem, max_per_view)
    if rows.size > 1500:
        raise ValueError(f"{rows.size} keypoints are too many for a similarity figure; lower max_per_view")
    E = embeddings
    A = graph.adjacency().toarray()[np.ix_(rows, rows)]
    S = E[rows] @ E[rows].T
    g = problem.gt_track[rows]
    X = ((g[:, None] == g[None, :]) & (g[:, None] >= 0)).astype(np.float64)
    np.fill_diagonal(X, 1.0)
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(14.0, 4.9), layout="constrained")
    panels = [(A, "input graph A (descriptor similarities)"), (S, "GCN output EEᵀ (clipped to [0, 1])"),
              (X, "ground truth XXᵀ")]
    for ax, (M, name) in zip(axes, panels):
        im = ax.imshow(M, vmin=0.0, vmax=1.0, cmap="magma", interpolation="nearest")
        for o in offsets[1:-1]:
            ax.axhline(o - 0.5, color="w", lw=0.8)
            ax.axvline(o - 0.5, color="w", lw=0.8)
        centers = (offsets[:-1] + offsets[1:]) / 2.0
        ax.set_xticks(centers)
        ax.set_xticklabels([f"view {v}" for v in range(len(centers))], fontsize=8)
        ax.set_yticks(centers)
        ax.set_yticklabels([f"view {v}" for v in range(len(centers))], fontsize=8, rotation=90, va="center")
        ax.set_title(name, fontsize=10)
    fig.colorbar(im, ax=list(axes), fraction=0.015, pad=0.01, shrink=0.9)
    shown = f"{rows.size} of {problem.n_keypoints}" if rows.size < problem.n_keypoints else f"all {rows.size}"
    fig.suptitle(title or f"{problem.name or 'problem'}: {shown} keypoints, views in blocks, "
                          f"ordered by ground-truth track", fontsize=11)
    return _save(fig, path)


def cross_view_similarities(E: np.ndarray, problem: Problem) -> Tuple[np.ndarray, np.ndarray]:
    """EEᵀ over pairs in different views: (same scene point, different points).

    "Different" pairs have both ends labelled (>= 0 or -1) and not the same point;
    unlabelled (-2) keypoints are left out.
    """
    gt = problem.gt_track
    if gt is None:
        raise ValueError(f"problem '{problem.name}' has no gt_track")
    same, diff = [], []
    for a in range(problem.n_views):
        for b in range(a + 1, problem.n_views):
            ia = np.arange(*problem.view_offsets[a:a + 2])
            ib = np.arange(*problem.view_offsets[b:b + 2])
            ia, ib = ia[gt[ia] >= -1], ib[gt[ib] >= -1]
            if not ia.size or not ib.size:
                continue
            S = E[ia] @ E[ib].T
            eq = (gt[ia][:, None] == gt[ib][None, :]) & (gt[ia][:, None] >= 0)
            same.append(S[eq])
            diff.append(S[~eq])
    cat = (lambda xs: np.concatenate(xs) if xs else np.zeros(0))  # noqa: E731
    return cat(same), cat(diff)


def plot_similarity_histograms(embeddings: Mapping[str, Sequence[np.ndarray]], problems: Sequence[Problem], path,
                               bins: int = 60, title: str = "") -> Path:
    """Histograms of EEᵀ for cross-view pairs of the same point vs different points, pooled
    over ``problems`` (labelled). ``embeddings``: label -> the (N_i, d) embeddings of each
    problem (e.g. one model's): one panel each, e.g. with and without the epipolar loss."""
    if any(p.gt_track is None for p in problems):
        raise ValueError("every problem of the histograms needs ground truth (gt_track)")
    if not problems:
        raise ValueError("no problem for the histograms")
    plt = _plt()
    fig, axes = plt.subplots(1, len(embeddings), figsize=(5.2 * len(embeddings), 3.9), squeeze=False)
    edges = np.linspace(-1.0, 1.0, bins + 1)
    for ax, (label, per_problem) in zip(axes[0], embeddings.items()):
        same, diff = [], []
        for E, p in zip(per_problem, problems):
            s, d = cross_view_similarities(E, p)
            same.append(s)
            diff.append(d)
        same, diff = np.concatenate(same), np.concatenate(diff)
        for vals, name, color in ((diff, "different points", "tab:blue"), (same, "same point", "tab:orange")):
            if vals.size:
                ax.hist(np.clip(vals, -1, 1), bins=edges, density=True, alpha=0.6, color=color,
                        label=f"{name} (n={vals.size}, mean {vals.mean():.2f})")
        ax.set_yscale("log")
        ax.set_xlabel("similarity  (EEᵀ)ᵢⱼ")
        ax.set_ylabel("density")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(title or f"cross-view similarities over {len(problems)} problem(s)", fontsize=11)
    fig.tight_layout()
    return _save(fig, path)
