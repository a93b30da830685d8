"""Run several methods on the same problems in one run and tabulate their scores.

Used by ``gcn-match eval`` and the benchmarks. Every method sees the same problems in
the same process; each gets one untimed warm-up solve (first calls of torch and BLAS
ops are slower), and runtimes are reported as medians. A method that refuses a problem
(e.g. a dense method above its size limit) is recorded as skipped with its reason.

Two kinds of scores: against the labels (``gt_track``: P, R, F1, ... of :mod:`.metrics`),
and — wherever the problem has cameras — against the true geometry, every predicted pair
(:mod:`.geometric_metrics`): geometric precision over all predicted pairs, the share far
(> 10 px) from the epipolar line, and pooled recall, a method's consistent pairs over the
union of every evaluated method's consistent pairs. Labels of pose scenes confirm only part
of the pairs a method predicts; the geometric scores see them all.

A method written ``SPEC@REVISION`` is solved by the package as it was at that git revision
(:mod:`.revision_solve`: before/after on the same problems and labels, in one table); it gets no
warm-up, its seconds are that solve's own, and a problem it refuses there is skipped like any other.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List, Sequence, Union

import numpy as np
from tqdm import tqdm

from .geometric_metrics import score_geometric
from .metrics import SCORE_KEYS, mean_scores, pr_curve, reference_rows, score_result, scored_pairs
from .problem import Problem, load_problem
from .revision_solve import solve_at_revision, split_revision
from . import solvers

__all__ = ["evaluate", "format_table"]

ProblemLike = Union[Problem, str, Path]


def evaluate(problems: Sequence[ProblemLike], methods: Sequence[str], progress: bool = True,
             with_reference_rows: bool = True) -> Dict:
    """Score every method on every problem.

    Problems need labels (``gt_track``) or cameras (K, R, t), or both.

    Returns a JSON-able report::

        {"problems": [names], "methods": {spec: {"describe": str, "per_problem": {name: scores},
                                                "mean": scores, "skipped": {name: reason},
                                                "pr": {"precision": [...], "recall": [...]},
                                                "geometric": {...}}}}

    ``geometric`` (only with posed problems) pools every posed problem's predicted pairs:
    pairs, consistent, precision, far (share > 10 px from the epipolar line), tracks3
    (consistent tracks of >= 3 keypoints), pooled_recall. Label scores are NaN on problems
    without labels.
    """
    loaded = [p if isinstance(p, Problem) else load_problem(p) for p in problems]
    for p in loaded:
        if p.gt_track is None and not p.has_poses:
            raise ValueError(f"problem '{p.name}' has neither gt_track nor cameras: cannot evaluate")
    methods = list(dict.fromkeys(methods))  # a row a method
    revisions = {m: split_revision(m) for m in methods}
    by_spec = {m: solvers.create(m) for m, (_, revision) in revisions.items() if revision is None}
    report: Dict = {"problems": [p.name for p in loaded], "methods": {}}
    if loaded:
        for solver in by_spec.values():
            _warm_up(solver, loaded[0])
    solved_at_revision = {m: solve_at_revision(spec, revision, loaded)
                          for m, (spec, revision) in revisions.items() if revision is not None}
    bar = tqdm(total=len(loaded) * len(methods), desc="eval", unit="solve", disable=not progress,
               leave=False)
    consistent_sets: Dict[str, Dict[str, set]] = {}
    for spec in methods:
        solver = by_spec.get(spec)
        per_problem, skipped, pooled, geometric = {}, {}, [], []
        consistent_sets[spec] = {}
        for i, p in enumerate(loaded):
            bar.set_postfix_str(f"{spec} {p.name}", refresh=False)
            try:
                result = solver.solve(p) if solver is not None else _solved(solved_at_revision[spec][i])
            except (ValueError, MemoryError) as exc:
                skipped[p.name] = str(exc)
            else:
                if p.gt_track is not None:
                    per_problem[p.name] = score_result(p, result)
                    pooled.append(scored_pairs(p, result))
                else:
                    per_problem[p.name] = {k: float("nan") for k in SCORE_KEYS}
                    per_problem[p.name]["seconds"] = result.seconds
                if p.has_poses:
                    g = score_geometric(p, result)
                    geometric.append(g.summary())
                    per_problem[p.name]["P_geo"] = g.precision
                    consistent_sets[spec][p.name] = set((g.rows[g.consistent] * p.n_keypoints
                                                         + g.cols[g.consistent]).tolist())
            bar.update()
        report["methods"][spec] = {"describe": solver.describe() if solver is not None else spec,
                                   "per_problem": per_problem,
                                   "mean": mean_scores(per_problem.values()), "skipped": skipped,
                                   "pr": _pooled_pr(pooled)}
        if geometric:
            report["methods"][spec]["geometric"] = _pooled_geometric(geometric)
    bar.close()
    _add_pooled_recall(report, consistent_sets)
    if with_reference_rows and loaded:
        refs = [reference_rows(p) for p in loaded]
        for row in ("identity", "all-zero"):
            report["methods"][row] = {"describe": row, "per_problem": {},
                                      "mean": mean_scores([r[row] for r in refs]), "skipped": {},
                                      "reference": True}
    return report


def _solved(result):
    """A result solved at another revision, or the refusal it stands for raised
    (:func:`.revision_solve.solve_at_revision`)."""
    if isinstance(result, Exception):
        raise result
    return result


def _warm_up(solver, problem: Problem) -> None:
    try:
        solver.solve(problem)
    except (ValueError, MemoryError):
        pass  # recorded when the timed run refuses too


def _pooled_geometric(summaries: List[Dict[str, float]]) -> Dict[str, float]:
    """Sums of the per-problem geometric summaries, precision and far share over all pairs."""
    pairs = sum(s["pairs"] for s in summaries)
    consistent = sum(s["consistent"] for s in summaries)
    far = sum(s["far"] * s["pairs"] for s in summaries if s["pairs"])
    return {"pairs": pairs, "consistent": consistent, "tracks3": sum(s["tracks3"] for s in summaries),
            "precision": consistent / pairs if pairs else float("nan"),
            "far": far / pairs if pairs else float("nan")}


def _add_pooled_recall(report: Dict, consistent_sets: Dict[str, Dict[str, set]]) -> None:
    """Each method's consistent pairs over the union of every method's, on the posed problems
    every method solved (the union is only as large as the methods evaluated together)."""
    common = set.intersection(*(set(sets) for sets in consistent_sets.values())) if consistent_sets else set()
    union = sum(len(set().union(*(sets[name] for sets in consistent_sets.values()))) for name in common)
    for spec, sets in consistent_sets.items():
        entry = report["methods"][spec].get("geometric")
        if entry is not None:
            mine = sum(len(sets[name]) for name in common)
            entry["pooled_recall"] = mine / union if union else float("nan")


def _pooled_pr(pooled: List) -> Dict[str, List[float]]:
    """Precision–recall over the pairs of all problems together, at most ~200 points."""
    if not pooled:
        return {"precision": [], "recall": []}
    scores = np.concatenate([s for s, _, _, _ in pooled])
    truth = np.concatenate([t for _, t, _, _ in pooled])
    n_true = sum(n for _, _, n, _ in pooled)
    n_pairs = sum(n for _, _, _, n in pooled)
    precision, recall, _ = pr_curve(scores, truth, n_true, n_pairs)
    step = max(1, len(precision) // 200)
    keep = np.r_[np.arange(0, len(precision), step), len(precision) - 1]
    return {"precision": precision[keep].round(5).tolist(), "recall": recall[keep].round(5).tolist()}


_COLUMNS = [("P", "P", "{:.3f}"), ("R", "R", "{:.3f}"), ("F1", "F1", "{:.3f}"), ("AP", "AP", "{:.3f}"),
            ("same_sim", "same", "{:.3f}"), ("diff_sim", "diff", "{:.4f}"), ("L1", "L1", "{:.4f}"),
            ("L2", "L2", "{:.4f}"), ("seconds", "median s", "{:.4f}")]


#: Geometric columns (posed problems): precision over all predicted pairs, pooled recall, far share.
_GEOMETRIC_COLUMNS = [("precision", "P geo", "{:.3f}"), ("pooled_recall", "R pool", "{:.3f}"),
                      ("far", "> 10 px", "{:.3f}")]


def format_table(report: Dict) -> str:
    """Markdown table: one row per method, sorted by F1 (by geometric precision when no problem
    has labels); trivial reference rows last. Geometric columns when any problem has cameras."""
    assert set(k for k, _, _ in _COLUMNS) <= set(SCORE_KEYS)
    geometric = any("geometric" in e for e in report["methods"].values())
    columns = _COLUMNS + (_GEOMETRIC_COLUMNS if geometric else [])
    header = "| method | " + " | ".join(h for _, h, _ in columns) + " | solved |"
    lines = [header, "|" + "---|" * (len(columns) + 2)]
    n = len(report["problems"])

    def rank(kv):
        f1 = kv[1]["mean"].get("F1", float("nan"))
        if math.isnan(f1):
            f1 = kv[1].get("geometric", {}).get("precision", -1.0)
        return kv[1].get("reference", False), -f1

    for spec, entry in sorted(report["methods"].items(), key=rank):
        values = dict(entry["mean"], **entry.get("geometric", {}))
        cells = []
        for key, _, fmt in columns:
            val = values.get(key)
            if entry.get("reference") and key == "seconds":
                val = None
            cells.append("–" if val is None or (isinstance(val, float) and math.isnan(val)) else fmt.format(val))
        solved = "–" if entry.get("reference") else f"{len(entry['per_problem'])}/{n}"
        lines.append(f"| {entry['describe']} | " + " | ".join(cells) + f" | {solved} |")
    for spec, entry in report["methods"].items():
        for name, reason in list(entry.get("skipped", {}).items())[:3]:
            lines.append(f"\n{spec} skipped {name}: {reason}")
    return "\n".join(lines)
