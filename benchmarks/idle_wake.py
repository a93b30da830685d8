#!/usr/bin/env python
"""What idling between windows costs: the same stream of windows solved back to back, and at the
camera rate with the CPU idle in between.

The matcher node solves a window and then waits for the next one: at 4 x 500 and 10 Hz the CPU
is idle ~60 % of the time. On this project's machine (a virtual machine whose idle vCPUs halt,
cpuidle ``haltpoll`` with no guest polling) a window that starts after such a pause can run
markedly slower than one solved straight after another, and that, not the node, makes the node's
tail (issue 12: p95 < 50 ms). This benchmark measures it without ROS: the window of
stage_breakdown's stream rows (``synthetic.rome16k``, SIFT-like, one :class:`StreamState`,
landmarks on, as the node) solved in rounds that alternate the modes (so drift hits all alike):

- back to back: the next window right after the last;
- 10 Hz, idle: windows every 100 ms, the thread asleep in between (the node's worker);
- 10 Hz, spin L ms: the same, but the thread busy-waits the last L ms before each window
  (what keeping the CPU out of its idle state would buy, at L / 100 ms of a core).

Usage::

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/idle_wake.py                 # ~1 min
    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/idle_wake.py --config 4x500 --rounds 8 --spin-ms 10 30
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.experiments import python_speed, results_header, run_note
from gcn_match_ros.stream import StreamState, solve_window

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_breakdown import rig_window  # noqa: E402  (the same window as its stream rows)

REPO = Path(__file__).resolve().parents[1]
PERIOD_S = 0.1  # 10 Hz
SLOW = 1.3  # a window slower than this times the back-to-back median counts as slow


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--solver", default="gcn")
    ap.add_argument("--config", default="4x500", help="views x keypoints per view")
    ap.add_argument("--rounds", type=int, default=6, help="rounds, each mode once a round")
    ap.add_argument("--windows", type=int, default=25, help="windows a mode a round")
    ap.add_argument("--spin-ms", type=float, nargs="*", default=[10.0, 30.0],
                    help="busy-wait before each paced window, ms (one mode each)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the node: 2)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "idle_wake.md")
    return ap


def _wait_until(deadline: float, spin_s: float) -> None:
    """Sleep until ``spin_s`` before ``deadline``, then busy-wait to it."""
    rest = deadline - spin_s - time.perf_counter()
    if rest > 0:
        time.sleep(rest)
    while time.perf_counter() < deadline:
        pass


def timed_windows(solver, problem, state: StreamState, n: int, stamp: int, pace_s: float, spin_s: float):
    """Wall seconds of ``n`` solve_window calls: back to back (``pace_s`` 0) or one every
    ``pace_s`` seconds, busy-waiting the last ``spin_s`` before each. Returns (times, next stamp)."""
    times = []
    deadline = time.perf_counter()
    for _ in range(n):
        if pace_s:
            deadline += pace_s
            _wait_until(deadline, spin_s)
        start = time.perf_counter()
        solve_window(solver, problem, state, stamp)
        times.append(time.perf_counter() - start)
        stamp += 10**8
    return times, stamp


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    views, keypoints = (int(x) for x in args.config.lower().split("x"))
    problem = rig_window(views, keypoints)
    solver, state = solvers.create(args.solver), StreamState()
    modes = [("back to back", 0.0, 0.0), ("10 Hz, idle between windows", PERIOD_S, 0.0)]
    modes += [(f"10 Hz, spin {ms:g} ms before each window", PERIOD_S, ms * 1e-3) for ms in args.spin_ms]
    speed_before = python_speed()
    t0 = time.monotonic()
    stamp = 0
    for _ in range(4):  # warm-up: model, first fits, first landmarks
        solve_window(solver, problem, state, stamp)
        stamp += 10**8
    times = {name: [] for name, _, _ in modes}
    for r in range(args.rounds):
        for name, pace, spin in (modes if r % 2 == 0 else modes[::-1]):
            got, stamp = timed_windows(solver, problem, state, args.windows, stamp, pace, spin)
            times[name] += got
        print(f"  round {r + 1}/{args.rounds}", flush=True)
    seconds = time.monotonic() - t0
    base = np.median(times["back to back"])
    lines = ["| mode | windows | p50 [ms] | p90 [ms] | p95 [ms] | max [ms] | slow windows (> "
             f"{SLOW:g}x back-to-back p50) | extra CPU [cores] |", "|---|---|---|---|---|---|---|---|"]
    for name, pace, spin in modes:
        t = 1e3 * np.asarray(times[name])
        lines.append(f"| {name} | {t.size} | {np.median(t):.1f} | {np.percentile(t, 90):.1f} | "
                     f"{np.percentile(t, 95):.1f} | {t.max():.1f} | {np.mean(t > 1e3 * SLOW * base):.0%} | "
                     f"{spin / pace if pace else 0:.2f} |")
    header = results_header("Idling between windows: solve time back to back and at 10 Hz", __file__,
                            argv, torch_threads=args.threads,
                            env=("OPENBLAS_NUM_THREADS",))
    text = ("\n".join(header) + f"\n\n{run_note(seconds, speed_before)}\n\n"
            f"{views} x {keypoints} (synthetic.rome16k, the same window each time, one StreamState, landmarks "
            f"on: solve_window's wall time), solver `{solver.describe()}`; {args.rounds} rounds of "
            f"{args.windows} windows a mode, the modes' order reversed every other round.\n\n"
            + "\n".join(lines) + "\n")
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
