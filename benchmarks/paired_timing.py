#!/usr/bin/env python
"""Which of two solvers is faster on the same windows: paired timing, window by window.

This project's 2-core machine changes speed by a third within minutes, more than most changes
move a solve: two whole benchmark runs, one per solver, compare the machine's states as much as
the solvers. Here both solvers solve the same stream of windows in one process, alternating
window by window (which goes first flips every pair), so each pair of solves sees the same
state; the result is the distribution of the paired differences (B - A): its median, a
bootstrap interval of its mean, and how many pairs B won.

Each solver keeps its own :class:`gcn_match_ros.stream.StreamState` (rig memory, landmarks), as
the node does, and solves the same synthetic window (``synthetic.rome16k``, SIFT-like, the
cameras named: ``stage_breakdown.rig_window``) every 100 ms of stream time, as stage_breakdown.py's
stream rows; the process keeps freed memory for the next window, as the node and stage_breakdown.py
do (:func:`gcn_match_ros.allocator.keep_freed_memory`).

Usage::

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/paired_timing.py gcn gcn:parallel=false
    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/paired_timing.py gcn "gcn:checkpoint=/tmp/x.pt" \\
        --config 4x500 --pairs 80 --out /tmp/paired_timing.md
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.allocator import keep_freed_memory
from gcn_match_ros.experiments import python_speed, results_header, write_results, run_note
from gcn_match_ros.metrics import paired_bootstrap
from gcn_match_ros.stream import StreamState, solve_window

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_breakdown import rig_window  # noqa: E402  (the same window as its stream rows)

REPO = Path(__file__).resolve().parents[1]
#: stages reported next to the total (gcn_match_ros.timing)
STAGES = ("graph", "network", "candidates", "edge_head", "rounding")
WARMUP = 4


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="solver spec A (the reference)")
    ap.add_argument("b", help="solver spec B")
    ap.add_argument("--config", default="4x500", help="views x keypoints per view")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "paired_timing.md")
    return ap


def paired_solves(spec_a: str, spec_b: str, views: int, keypoints: int, pairs: int) -> dict:
    """Wall seconds and stage seconds of ``pairs`` alternating solve_window calls of each solver.

    Returns: {"a" | "b": {"total": (pairs,) array, stage: (pairs,) array}}."""
    problem = rig_window(views, keypoints)
    made = {"a": (solvers.create(spec_a), StreamState()), "b": (solvers.create(spec_b), StreamState())}
    for solver, state in made.values():
        for w in range(WARMUP):
            solve_window(solver, problem, state, w * 10**8)
    out = {k: {"total": [], **{s: [] for s in STAGES}} for k in made}
    for p in range(pairs):
        stamp = (WARMUP + p) * 10**8
        for k in (("a", "b") if p % 2 == 0 else ("b", "a")):
            solver, state = made[k]
            start = time.perf_counter()
            result, _ = solve_window(solver, problem, state, stamp)
            out[k]["total"].append(time.perf_counter() - start)
            for s in STAGES:
                out[k][s].append(result.timings.get(s, 0.0))
        if (p + 1) % 20 == 0:
            print(f"  {p + 1}/{pairs} pairs", flush=True)
    return {k: {s: np.asarray(v) for s, v in d.items()} for k, d in out.items()}


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    keep_freed_memory()
    views, keypoints = (int(x) for x in args.config.lower().split("x"))
    speed_before = python_speed()
    t0 = time.monotonic()
    r = paired_solves(args.a, args.b, views, keypoints, args.pairs)
    seconds = time.monotonic() - t0
    a, b = 1e3 * r["a"]["total"], 1e3 * r["b"]["total"]
    diff = b - a
    mean, lo, hi = paired_bootstrap(b, a)
    lines = ["| solver | solve p50 [ms] | " + " | ".join(f"{s} p50" for s in STAGES) + " |",
             "|---" * (len(STAGES) + 2) + "|"]
    for key, spec in (("a", args.a), ("b", args.b)):
        stages = " | ".join(f"{1e3 * np.median(r[key][s]):.1f}" for s in STAGES)
        lines.append(f"| {key.upper()}: `{spec}` | {1e3 * np.median(r[key]['total']):.1f} | {stages} |")
    verdict = (f"B - A per pair: median {np.median(diff):+.2f} ms, mean {mean:+.2f} ms (95 % bootstrap interval "
               f"{lo:+.2f} .. {hi:+.2f}); B faster in {int((diff < 0).sum())} of {diff.size} pairs.")
    header = results_header("Paired timing of two solvers (window by window)", __file__,
                            argv, torch_threads=args.threads,
                            env=("OPENBLAS_NUM_THREADS",))
    text = ("\n".join(header) + f"\n\n{run_note(seconds, speed_before)}\n\n"
            f"{views} x {keypoints} (synthetic.rome16k, the same window every 100 ms of stream time, each "
            f"solver with its own StreamState), {args.pairs} pairs after {WARMUP} warm-up windows each; "
            "solve_window's wall time (landmarks included); stages: medians of gcn_match_ros.timing.\n\n"
            + "\n".join(lines) + f"\n\n{verdict}\n")
    print(text)
    write_results(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
