#!/usr/bin/env python
"""Solver settings on generated scenes: the guard "generated scenes unchanged or better" (issue 11).

Scores each method on generated windows (gcn_match_ros.data.synthetic: the rome16k and partial
presets, SIFT-like descriptors, 3, 4 and 6 views; seeds [11, 0..--seeds-1], the goal's windows, or
[11, --first-seed..], windows of their own to choose a setting on) against their exact
labels, and reports mean F1 and precision per preset and window size, with each method's F1
change against the first method and, per preset over all sizes, the 95 % bootstrap interval of
that change (paired by window: metrics.paired_bootstrap), so a change can be told from noise. A
rule for real scenes that assumes what generated scenes do not hold (a point inside a view is
seen there: partial visibility breaks it) shows here. A method written SPEC@REVISION is solved
by the package as it was at that git revision (gcn_match_ros.revision_solve): the goal's "unchanged"
means against the solver of the day it was set (issue 11: gcn@a482093), not today's code with an
older model.

Usage::

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/generated_eval.py --methods "gcn;gcn:support_threshold=0.8"
    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/generated_eval.py --seeds 30 --first-seed 1000 \
        --methods "gcn;gcn:checkpoint=candidate.pt" --out /tmp/choice.md   # choosing, not the goal's windows
    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/generated_eval.py --seeds 30 --methods "gcn@a482093;gcn"
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.experiments import results_header, solved_at_revision, write_results
from gcn_match_ros.metrics import paired_bootstrap, score_result
from gcn_match_ros.revision_solve import split_revision

REPO = Path(__file__).resolve().parents[1]
PRESETS = ("rome16k", "partial")
VIEWS = (3, 4, 6)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", default="gcn",
                    help="solver specs separated by ';' (the first is the reference); SPEC@REVISION: solved by "
                         "the package at that git revision")
    ap.add_argument("--seeds", type=int, default=6, help="windows per preset and size")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="seeds [11, first..first+seeds-1]: windows other than the goal's (0..), to choose on")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "generated_eval.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()
    specs = [m for m in args.methods.split(";") if m]
    windows = {(preset, views): [synthetic.random_scene_problem(synthetic.preset(preset, views, "sift"),
                                                                np.random.default_rng([11, seed]))
                                 for seed in range(args.first_seed, args.first_seed + args.seeds)]
               for preset in PRESETS for views in VIEWS}
    problems = [p for ps in windows.values() for p in ps]
    results = {}  # method -> one result per problem, in the order of `problems`
    for m in specs:
        spec, revision = split_revision(m)
        if revision is None:
            solver = solvers.create(spec)
            results[m] = [solver.solve(p) for p in problems]
        else:
            results[m] = solved_at_revision(m, problems)
    rows = []
    per_window = {(preset, m): [] for preset in PRESETS for m in specs}  # F1 of every window
    at = 0
    for (preset, views), ps in windows.items():
        scores = {m: [(s["F1"], s["P"]) for s in map(score_result, ps, results[m][at:at + len(ps)])] for m in specs}
        at += len(ps)
        for m in specs:
            f1, p = np.mean(scores[m], axis=0)
            rows.append((preset, views, m, f1, p))
            per_window[preset, m] += [x[0] for x in scores[m]]
        print(f"{preset} {views} views: " + ", ".join(f"{m} F1 {np.mean([x[0] for x in scores[m]]):.4f}"
                                                 for m in specs), flush=True)
    reference = {(r[0], r[1]): r[3] for r in rows if r[2] == specs[0]}
    lines = results_header("Solver settings on generated scenes", __file__, argv, torch_threads=1,
                           env=("OPENBLAS_NUM_THREADS",))
    lines += [f"Generated windows (data.synthetic presets, SIFT-like descriptors), {args.seeds} a preset and size "
              f"(seeds [11, {args.first_seed}..{args.first_seed + args.seeds - 1}]); mean F1 / precision against the "
              f"exact labels; change: F1 against {specs[0]}.", "",
              "| preset | views | method | F1 | P | change |", "|---|---|---|---|---|---|"]
    for preset, views, m, f1, p in rows:
        lines.append(f"| {preset} | {views} | {m} | {f1:.4f} | {p:.4f} | {f1 - reference[(preset, views)]:+.4f} |")
    if len(specs) > 1:
        lines += ["", f"F1 change against {specs[0]} over all sizes of a preset (mean over windows; 95 % bootstrap "
                      "interval, windows paired):", ""]
        for preset in PRESETS:
            for m in specs[1:]:
                mean, lo, hi = paired_bootstrap(per_window[preset, m], per_window[preset, specs[0]])
                lines.append(f"- {preset}, {m}: {mean:+.4f} [{lo:+.4f}, {hi:+.4f}], "
                             f"{len(per_window[preset, m])} windows")
    lines += ["", f"Total wall time {time.perf_counter() - started:.0f} s."]
    write_results(args.out, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
