#!/usr/bin/env python
"""Where one window's solve spends its time: per-stage milliseconds, offline, one process.

Solves synthetic windows (``synthetic.rome16k``: SIFT-like 128-D descriptors of a 3D scene,
the node benchmark's input) of every (views, keypoints per view) configuration with each
solver, in ``--repeats`` rounds after a warm-up (each round solves once with every solver of
the configuration, so that the machine's drift reaches all alike), and reports the median of
every stage that :mod:`gcn_match_ros.timing` records (similarity, graph, candidates, geometry,
network, edge_head, rounding, match), the median total, the total relative to the first
solver's in the same round (median over the rounds; ``nn`` by default: the issue's "x nn"
figure) and the peak resident memory growth of one solve after the warm-up (``tracemalloc``
does not see torch's allocator, so the process RSS is read; the peak is the process's, so a
solve shows only what it adds to the peaks before it).

Every solver runs twice: each window on its own ("cold": every two-view model fitted), and
as a stream of that rig (one :class:`gcn_match_ros.stream.StreamState` across the repeats,
cameras named: the remembered two-view models are re-checked and reused,
:mod:`gcn_match_ros.edges.rig_memory`) — what the matcher node does with a fixed rig. The
stream also gives each window's keypoints their persistent landmarks, as the node does
(:func:`gcn_match_ros.stream.solve_window`): the time that takes after the solve (the landmark
search's chunks still left, then the association) is its own column, outside the solve's total,
with the ratio of the two (issue 13: within 20%).

Usage::

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/stage_breakdown.py
    ./run.sh python benchmarks/stage_breakdown.py --configs 4x500 10x1000 --solvers nn gcn --repeats 5
    # on a machine with a GPU: the network there, the rest on two CPU cores
    taskset -c 0,1 ./run.sh python benchmarks/stage_breakdown.py --solvers nn gcn gcn:device=cuda

``gcn`` computes its candidate edges (with their similarity blocks and two-view geometry) on a
second thread beside its graph and network (``parallel``, the default; gcn_match_ros.threads):
its stages are then the two threads' times and add up to more than the total, and ``waiting``
is the time the solve idled for the second thread. ``gcn:parallel=false`` gives the one-thread breakdown.

The process keeps the memory a window frees for the next one, as the node does by default
(:func:`gcn_match_ros.allocator.keep_freed_memory`; ``--keep-freed-memory false``: glibc's own
thresholds, under which windows fault the same pages in again).

With ``device=cuda`` the stages run asynchronously on the GPU until a result is copied back, so
the GPU's time lands in the stage that copies (the edge head); the totals are exact.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import plots, solvers
from gcn_match_ros.allocator import keep_freed_memory
from gcn_match_ros.data.synthetic import random_scene_problem, rome16k
from gcn_match_ros.experiments import python_speed, results_header, write_results, speed_note
from gcn_match_ros.stream import StreamState, solve_window

REPO = Path(__file__).resolve().parents[1]
STAGES = ("similarity", "graph", "candidates", "geometry", "network", "edge_head", "rounding", "match", "waiting")
WORK = STAGES[:-1]  # "waiting": the solve idling for its second thread, drawn as no work


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", nargs="+", default=["4x500", "8x500", "4x1000", "10x1000"],
                   help="VIEWSxKEYPOINTS windows")
    p.add_argument("--solvers", nargs="+", default=["nn", "gcn", "gcn:parallel=false"], help="solver specs; the first is the reference")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", type=int, default=2, help="torch threads")
    p.add_argument("--keep-freed-memory", choices=("true", "false"), default="true",
                   help="glibc keeps freed memory for the next window (gcn_match_ros.allocator), as the node "
                        "does by default (its keep_freed_memory parameter)")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "stage_breakdown.md")
    p.add_argument("--append", action="store_true")
    return p


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rig_window(views: int, keypoints: int):
    """The synthetic window these timings solve (``synthetic.rome16k``, SIFT-like, seed 0), its
    cameras named as a rig's so that a stream keeps their memory."""
    problem = random_scene_problem(rome16k(views, n_points=keypoints), rng=0)
    problem.camera_ids = tuple(f"cam{v}" for v in range(views))
    return problem


class Variant:
    """One solver on one window, alone (``stream`` False) or as a stream of that rig, with its
    timings so far."""

    def __init__(self, spec: str, problem, stream: bool) -> None:
        self.problem = problem
        self.solver = solvers.create(spec)
        self.stream = stream
        self.state = StreamState() if stream else None
        self.totals, self.landmarks, self.stages = [], [], {s: [] for s in STAGES}
        self.spec = self.solver.describe() + (" (stream)" if stream else "")

    def solve(self, k: int) -> None:
        """The k-th solve, timed (the stream's stamps 100 ms apart)."""
        t0 = time.perf_counter()
        if self.stream:  # the node's path: the solve, then the landmark association
            result, landmarks = solve_window(self.solver, self.problem, self.state, (k + 1) * 10**8)
            self.landmarks.append(landmarks.seconds)
            self.totals.append(result.seconds)
        else:
            result = self.solver.solve(self.problem)
            self.totals.append(time.perf_counter() - t0)
        for s in STAGES:
            self.stages[s].append(result.timings.get(s, 0.0))

    def warm_up(self) -> float:
        """One untimed solve (model load, first-call allocations, the first fits and landmarks),
        then one more; returns the peak resident memory growth of that second solve [MB]."""
        self.solve(-1)
        before = _rss_mb()
        self.solve(0)
        self.totals.clear()
        self.landmarks.clear()
        for times in self.stages.values():
            times.clear()
        return _rss_mb() - before


def measure(specs, views: int, keypoints: int, repeats: int) -> list:
    """Every solver of ``specs``, alone and as a stream, on the same window: each warmed up in
    turn, then ``repeats`` rounds that solve once with each (so the machine's drift, a quarter
    within minutes on this project's VM, reaches all alike).

    Returns: per variant, {"spec", "views", "keypoints", "total" (median s), "stages" (medians),
    "landmarks" (median s or None), "rss_growth" (MB), "ratio" (the median of its time over the
    first variant's in the same round)}."""
    problem = rig_window(views, keypoints)
    variants = [Variant(spec, problem, stream) for spec in specs for stream in (False, True)]
    growth = [v.warm_up() for v in variants]
    for k in range(repeats):
        for v in variants:
            v.solve(k + 1)
    first = np.asarray(variants[0].totals)
    return [{"spec": v.spec, "views": views, "keypoints": v.problem.n_keypoints,
             "total": float(np.median(v.totals)), "stages": {s: float(np.median(x)) for s, x in v.stages.items()},
             "landmarks": float(np.median(v.landmarks)) if v.landmarks else None, "rss_growth": g,
             "ratio": float(np.median(np.asarray(v.totals) / first))}
            for v, g in zip(variants, growth)]


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    kept = args.keep_freed_memory == "true" and keep_freed_memory()
    speed_before = python_speed()
    rows = []
    for cfg in args.configs:
        views, keypoints = (int(x) for x in cfg.lower().split("x"))
        for r in measure(args.solvers, views, keypoints, args.repeats):
            rows.append(r)
            print(f"{views} x {keypoints}: {r['spec']}: {1e3 * r['total']:.1f} ms ({r['ratio']:.2f}x)", flush=True)
    head = ("| window | solver | " + " | ".join(STAGES) + " | total [ms] | x first | landmarks [ms] | "
            "with / without landmarks | peak RSS growth [MB] |")
    lines = [head, "|" + "---|" * (len(STAGES) + 7)]
    for r in rows:
        cells = " | ".join(f"{1e3 * r['stages'][s]:.1f}" for s in STAGES)
        lm = r["landmarks"]
        lm_cells = "– | –" if lm is None else f"{1e3 * lm:.1f} | {(r['total'] + lm) / r['total']:.2f}"
        lines.append(f"| {r['views']} x {r['keypoints'] // r['views']} | {r['spec']} | {cells} | "
                     f"{1e3 * r['total']:.1f} | {r['ratio']:.2f} | {lm_cells} | {r['rss_growth']:.0f} |")
    table = "\n".join(lines)
    print(table)
    windows, wall = {}, {}
    for r in rows:
        label = f"{r['views']} x {r['keypoints'] // r['views']}"
        stages = {name: 1e3 * r["stages"][name] for name in WORK}
        stages["other"] = max(0.0, 1e3 * r["total"] - sum(stages.values()) - 1e3 * r["stages"]["waiting"])
        windows.setdefault(label, {})[r["spec"]] = stages
        wall.setdefault(label, {})[r["spec"]] = 1e3 * r["total"]
    figure = plots.plot_stage_times(windows, args.out.with_suffix(".png"), wall=wall,
                                    title="Where one window's time goes (offline, median; 'other': outside the stages)")
    gpu = [f"GPU: {torch.cuda.get_device_name()}"] if torch.cuda.is_available() else []
    header = results_header("Per-stage time of one window (offline)", __file__,
                            argv, torch_threads=args.threads,
                            machine_extra=gpu, env=("OPENBLAS_NUM_THREADS",))
    text = ("\n".join(header) + f"\n\nMedian of {args.repeats} rounds after a warm-up, each round one solve with every row's solver of the "
              "window in turn; 'x first': the median over the rounds of the total over the first row's in the same "
              "round; stages in ms, exclusive of nested "
              "stages (gcn_match_ros.timing; gcn's candidates, with their similarity and geometry, run on a second "
              "thread beside its graph and network: its stages then add up to more than its total, and 'waiting' "
              "is the time the solve idled for that thread; gcn:parallel=false is the same solve on one thread); windows: synthetic.rome16k, SIFT-like descriptors. Stream rows "
              "also give the window's keypoints their landmarks, as the node does (stream.solve_window, the "
              "same still scene every 100 ms: every landmark continues): 'landmarks' is the time they take "
              "after the solve (the search's chunks still left, the association), outside the total "
              "(issue 13's goal: with / without <= 1.20). "
              + ("Freed memory kept for the next window, as the node keeps it (gcn_match_ros.allocator). " if kept
                 else "glibc's own malloc thresholds (freed memory given back between windows). ")
              + f"Figure: {figure.name}. {speed_note(speed_before, python_speed())}\n\n"
            + table + "\n")
    write_results(args.out, text, append=args.append)
    return 0


if __name__ == "__main__":
    sys.exit(main())
