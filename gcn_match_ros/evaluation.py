"""Run several methods on the same problems in one run and tabulate their scores.

Used by ``gcn-match eval`` and the benchmarks. Every method sees the same problems in
the same process; each gets one untimed warm-up solve (first calls of torch and BLAS
ops are slower), and runtimes are reported as medians. A method that refuses a problem
(e.g. a dense method above its size limit) is recorded as skipped with its reason.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List, Sequence, Union

import numpy as np
from tqdm import tqdm

from .metrics import SCORE_KEYS, mean_scores, pr_curve, reference_rows, score_result, scored_pairs
from .problem import Problem, load_problem
from . import solvers

__all__ = ["evaluate", "format_table"]

ProblemLike = Union[Problem, str, Path]


def evaluate(problems: Sequence[ProblemLike], methods: Sequence[str], progress: bool = True,
             with_reference_rows: bool = True) -> Dict:
    """Score every method on every problem.

    Returns a JSON-able report::

        {"problems": [names], "methods": {spec: {"describe": str, "per_problem": {name: scores},
                                                "mean": scores, "skipped": {name: reason},
                                                "pr": {"precision": [...], "recall": [...]}}}}
    """
    loaded = [p if isinstance(p, Problem) else load_problem(p) for p in problems]
    for p in loaded:
        if p.gt_track is None:
            raise ValueError(f"problem '{p.name}' has no gt_track: cannot evaluate")
    by_spec = {spec: solvers.create(spec) for spec in methods}
    report: Dict = {"problems": [p.name for p in loaded], "methods": {}}
    if loaded:
        for solver in by_spec.values():
            _warm_up(solver, loaded[0])
    bar = tqdm(total=len(loaded) * len(by_spec), desc="eval", unit="solve", disable=not progress,
               leave=False)
    for spec, solver in by_spec.items():
        per_problem, skipped, pooled = {}, {}, []
        for p in loaded:
            bar.set_postfix_str(f"{spec} {p.name}", refresh=False)
            try:
                result = solver.solve(p)
            except (ValueError, MemoryError) as exc:
                skipped[p.name] = str(exc)
            else:
                per_problem[p.name] = score_result(p, result)
                pooled.append(scored_pairs(p, result))
            bar.update()
        report["methods"][spec] = {"describe": solver.describe(), "per_problem": per_problem,
                                   "mean": mean_scores(per_problem.values()), "skipped": skipped,
                                   "pr": _pooled_pr(pooled)}
    bar.close()
    if with_reference_rows and loaded:
        refs = [reference_rows(p) for p in loaded]
        for row in ("identity", "all-zero"):
            report["methods"][row] = {"describe": row, "per_problem": {},
                                      "mean": mean_scores([r[row] for r in refs]), "skipped": {},
                                      "reference": True}
    return report


def _warm_up(solver, problem: Problem) -> None:
    try:
        solver.solve(problem)
    except (ValueError, MemoryError):
        pass  # recorded when the timed run refuses too


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


def format_table(report: Dict) -> str:
    """Markdown table: one row per method, sorted by F1; trivial reference rows last."""
    assert set(k for k, _, _ in _COLUMNS) <= set(SCORE_KEYS)
    header = "| method | " + " | ".join(h for _, h, _ in _COLUMNS) + " | solved |"
    lines = [header, "|" + "---|" * (len(_COLUMNS) + 2)]
    n = len(report["problems"])
    entries = sorted(report["methods"].items(),
                     key=lambda kv: (kv[1].get("reference", False), -kv[1]["mean"].get("F1", -1)))
    for spec, entry in entries:
        mean = entry["mean"]
        cells = []
        for key, _, fmt in _COLUMNS:
            val = mean.get(key)
            if entry.get("reference") and key == "seconds":
                val = None
            cells.append("–" if val is None or (isinstance(val, float) and math.isnan(val)) else fmt.format(val))
        solved = "–" if entry.get("reference") else f"{len(entry['per_problem'])}/{n}"
        lines.append(f"| {entry['describe']} | " + " | ".join(cells) + f" | {solved} |")
    for spec, entry in report["methods"].items():
        for name, reason in list(entry.get("skipped", {}).items())[:3]:
            lines.append(f"\n{spec} skipped {name}: {reason}")
    return "\n".join(lines)
