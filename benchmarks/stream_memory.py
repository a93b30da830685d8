#!/usr/bin/env python
"""A solver's stream over many windows: process memory, page faults and window time, 100 windows a row.

The node solves window after window for hours, so whatever one window leaves behind adds up.
This solves one synthetic rig window (``synthetic.rome16k``, SIFT-like descriptors, cameras named
as a rig's) again and again as one stream (:func:`gcn_match_ros.stream.solve_window`: rig memory,
persistent landmarks), back to back, freed memory kept as the node keeps it
(:func:`gcn_match_ros.allocator.keep_freed_memory`), and prints per 100 windows: the resident
memory at the end, glibc's heap (held and in use, ``mallinfo2``), minor page faults a window,
the cyclic garbage collector's full passes, and the window's time (median, p95).

Memory that stays flat with few faults means each window frees what it made. A heap in use that
grows means something outlives its window (state that grows, or arrays in a reference cycle waiting
for the cyclic collector); a heap held that grows while the share in use does not means it fragments.

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/stream_memory.py --cameras 8 --keypoints 500   # ~1 min
"""
from __future__ import annotations

import argparse
import ctypes
import gc
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.allocator import keep_freed_memory
from gcn_match_ros.experiments import resident_memory_mb, results_header, write_results
from gcn_match_ros.libc import c_function
from gcn_match_ros.stream import StreamState, solve_window

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_breakdown import rig_window  # noqa: E402  (the same window as its stream rows)

REPO = Path(__file__).resolve().parents[1]
ROW = 100  # windows a row
MANY_FAULTS = 300  # page faults of a window that faulted fresh memory in (>= 1.2 MB), counted apart


class _MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]


def _heap_mb():
    """(held, in use) MB of glibc's heap over all arenas plus its own mappings; (nan, nan) where
    the C library has no ``mallinfo2``."""
    mallinfo2 = c_function("mallinfo2", (), _MallInfo2)
    if mallinfo2 is None:
        return float("nan"), float("nan")
    m = mallinfo2()
    return (m.arena + m.hblkhd) / 2**20, (m.uordblks + m.hblkhd) / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--solver", default="gcn")
    ap.add_argument("--cameras", type=int, default=8)
    ap.add_argument("--keypoints", type=int, default=500, help="keypoints per view")
    ap.add_argument("--windows", type=int, default=600, help="windows measured, after one warm-up window")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "stream_memory.md")
    args = ap.parse_args(argv)
    if args.windows < ROW:
        ap.error(f"--windows must be at least {ROW}")
    keep_freed_memory()
    problem = rig_window(args.cameras, args.keypoints)
    solver, state = solvers.create(args.solver), StreamState()
    full_passes = []
    gc.callbacks.append(lambda phase, info: full_passes.append(1) if phase == "stop" and info["generation"] == 2 else None)
    solve_window(solver, problem, state, 0)  # model, compiled code, the rig's first fits
    start_rss, times, faults, rows = resident_memory_mb(), [], [], []
    for k in range(1, args.windows + 1):
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        t0 = time.perf_counter()
        solve_window(solver, problem, state, k * 10**8)
        times.append(time.perf_counter() - t0)
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
        if k % ROW == 0:
            held, in_use = _heap_mb()
            ms = 1e3 * np.asarray(times[-ROW:])
            rows.append((k - ROW + 1, k, resident_memory_mb(), held, in_use, float(np.mean(faults[-ROW:])),
                         int(np.sum(np.asarray(faults[-ROW:]) > MANY_FAULTS)), len(full_passes),
                         float(np.median(ms)), float(np.percentile(ms, 95))))
            print(f"windows {k - ROW + 1}-{k}: RSS {rows[-1][2]:.0f} MB, {rows[-1][5]:.0f} faults a window, "
                  f"p50 {rows[-1][8]:.1f} ms", flush=True)
    lines = ["| windows | RSS at the end [MB] | heap held / in use [MB] | page faults a window (mean) | "
             f"windows with > {MANY_FAULTS} faults | full GC passes so far | window p50 / p95 [ms] |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {a}-{b} | {rss:.0f} | {held:.0f} / {used:.0f} | {f:.0f} | {many} | {gcs} | {p50:.1f} / {p95:.1f} |"
              for a, b, rss, held, used, f, many, gcs, p50, p95 in rows]
    header = results_header("A solver's stream: memory, page faults and window time", __file__, argv,
                            torch_threads=torch.get_num_threads(), env=("OPENBLAS_NUM_THREADS",))
    note = (f"Solver `{solver.describe()}`, one {args.cameras} x {args.keypoints} window (synthetic.rome16k, "
            f"SIFT-like descriptors) solved {args.windows} times back to back as one stream with landmarks, after one "
            f"warm-up window (RSS then {start_rss:.0f} MB); freed memory kept as the node keeps it. Heap: glibc's "
            "(mallinfo2) over all arenas and its own mappings; page faults: minor faults of the process during a "
            "window; full GC passes: the cyclic collector's generation-2 collections since the stream began (its warm-up window included).")
    write_results(args.out, "\n".join(header) + "\n\n" + note + "\n\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
