#!/usr/bin/env python
"""What idling between windows costs: the same stream of windows solved back to back, and at the
camera rate with the CPU idle in between.

The matcher node solves a window and then waits for the next one: at 4 x 500 and 10 Hz the CPU
is idle ~60 % of the time. On this project's machine (a 2-core VM whose guest kernel packs light
loads onto few CPUs, ``sched_vcpu_pack``) a window that starts after such a pause runs its two
threads on one core until the load has lasted, markedly slower than one solved straight after
another, and that, not the node, makes the node's tail (issue 12: p95 < 50 ms). This benchmark
measures it without ROS: the window of
stage_breakdown's stream rows (``synthetic.rome16k``, SIFT-like, one :class:`StreamState`,
landmarks on, as the node) solved in rounds that alternate the modes (so drift hits all alike):

- back to back: the next window right after the last;
- 10 Hz, idle: windows every 100 ms, the thread asleep in between (the node's worker);
- 10 Hz, spin L ms: the same, but the thread busy-waits the last L ms before each window
  (what keeping the CPU out of its idle state would buy, at L / 100 ms of a core);
- pinned: back to back and at 10 Hz with the solve's two threads each on a CPU of its own
  (:func:`gcn_match_ros.threads.pinned_solve_threads`, the node's ``cpu_affinity``).

The modes not pinned place the threads as the solver does: ``gcn`` keeps them on two CPUs chosen
for every window (:func:`gcn_match_ros.threads.kept_apart`), ``--solver gcn:keep_apart=false``
leaves them to the OS (what every mode but the pinned ones measured before that placement).

Each mode also reports the process's CPU time a window (both threads): where two busy threads
share one core, a window's wall time follows it. A second table checks the machine for that
without the matcher: bursts of a fixed compiled loop (``--burst-ms`` on one core) run on two
threads at once (the caller and a long-lived worker, as the solver's second thread), one burst
after another for ``PAUSE_S`` from right after a pause of ``PAUSE_S``, or back to back; the two
threads placed by the OS, or pinned. Their wall time against one thread's burst alone is 1.0
where the two threads get a core each and 2.0 where they share one.

Usage::

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/idle_wake.py                 # ~1 min
    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/idle_wake.py --config 4x500 --rounds 8 --spin-ms 10 30
"""
from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from pathlib import Path

import numba
import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.experiments import python_speed, results_header, write_results, run_note
from gcn_match_ros.stream import StreamState, solve_window
from gcn_match_ros.threads import pinned_solve_threads, solve_cpus

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_breakdown import rig_window  # noqa: E402  (the same window as its stream rows)

REPO = Path(__file__).resolve().parents[1]
PERIOD_S = 0.1  # 10 Hz
SLOW = 1.3  # a window slower than this times the back-to-back median counts as slow
PAUSE_S = 0.07  # the idle time before a window at 10 Hz (a 4 x 500 window takes ~30 ms)
#: time since the pause [ms] over which the burst ratios are summarised
SINCE_PAUSE_MS = (0, 10, 20, 30, 40, 60, 80)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--solver", default="gcn")
    ap.add_argument("--config", default="4x500", help="views x keypoints per view")
    ap.add_argument("--rounds", type=int, default=6, help="rounds, each mode once a round")
    ap.add_argument("--windows", type=int, default=25, help="windows a mode a round")
    ap.add_argument("--spin-ms", type=float, nargs="*", default=[30.0],
                    help="busy-wait before each paced window, ms (one mode each)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (the node: 2)")
    ap.add_argument("--burst-ms", type=float, default=1.0, help="one burst of the machine check, ms on one core")
    ap.add_argument("--pauses", type=int, default=30, help="pauses of the machine check, each placement")
    ap.add_argument("--cpu-affinity", type=int, default=0, help="first CPU of the pinned modes (cpu_affinity)")
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
    """Wall and process CPU seconds of ``n`` solve_window calls: back to back (``pace_s`` 0) or
    one every ``pace_s`` seconds, busy-waiting the last ``spin_s`` before each.

    Returns: (wall times, CPU times, next stamp)."""
    times, cpu = [], []
    deadline = time.perf_counter()
    for _ in range(n):
        if pace_s:
            deadline += pace_s
            _wait_until(deadline, spin_s)
        start, start_cpu = time.perf_counter(), time.process_time()
        solve_window(solver, problem, state, stamp)
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        stamp += 10**8
    return times, cpu, stamp


@numba.njit(nogil=True, cache=True)
def _burn(n: int) -> float:
    """A fixed compiled loop that releases the GIL (n steps)."""
    total = 0.0
    for i in range(n):
        total += (i % 7) * 1e-9
    return total


class _BurstPartner:
    """A long-lived second thread that runs one burst of :func:`_burn` each time it is asked,
    on CPU ``cpu`` alone (None: where the OS places it)."""

    def __init__(self, steps: int, cpu=None) -> None:
        self._steps, self._cpu = steps, cpu
        self._go, self._done = threading.Semaphore(0), threading.Semaphore(0)
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        if self._cpu is not None:
            os.sched_setaffinity(0, {self._cpu})
        while True:
            self._go.acquire()
            _burn(self._steps)
            self._done.release()

    def together(self) -> float:
        """Wall seconds of one burst on this thread and one on the partner at once."""
        start = time.perf_counter()
        self._go.release()
        _burn(self._steps)
        self._done.acquire()
        return time.perf_counter() - start


def burst_steps(burst_s: float):
    """Steps of :func:`_burn` that take ``burst_s`` on one thread, and the seconds they take."""
    _burn(10)
    steps = 10**6
    alone = np.median([_timed_burn(steps) for _ in range(20)])
    steps = max(1, int(steps * burst_s / alone))
    return steps, float(np.median([_timed_burn(steps) for _ in range(50)]))


def two_thread_bursts(steps: int, alone: float, pauses: int, cpus=None):
    """Two threads' bursts (this thread's and a partner's), one after another for ``PAUSE_S``
    from right after each of ``pauses`` pauses of ``PAUSE_S``, and as many back to back;
    ``cpus``: (this thread's CPU, the partner's), else where the OS places them.

    Returns: ([(ms since the pause, wall / alone)] after pauses, [wall / alone] back to back)."""
    mine = os.sched_getaffinity(0)
    if cpus is not None:
        os.sched_setaffinity(0, {cpus[0]})
    try:
        partner = _BurstPartner(steps, None if cpus is None else cpus[1])
        after_pause, back_to_back = [], []
        for _ in range(pauses):
            time.sleep(PAUSE_S)
            start = time.perf_counter()
            while time.perf_counter() - start < PAUSE_S:
                since = time.perf_counter() - start
                after_pause.append((1e3 * since, partner.together() / alone))
        while len(back_to_back) < len(after_pause):
            back_to_back.append(partner.together() / alone)
    finally:
        os.sched_setaffinity(0, mine)
    return after_pause, back_to_back


def _placed(pin: bool, first_cpu: int):
    """With ``pin``: this thread and the second thread pinned inside the block, as the node's worker
    (:func:`pinned_solve_threads`)."""
    return pinned_solve_threads(first_cpu) if pin else contextlib.nullcontext()


def _timed_burn(steps: int) -> float:
    start = time.perf_counter()
    _burn(steps)
    return time.perf_counter() - start


def burst_table(runs: dict) -> list:
    """Markdown lines: the two threads' burst time against one burst alone (p50 / p90), by time
    since the pause, for each placement of ``runs`` (name -> :func:`two_thread_bursts`'s result)."""
    lines = ["| two threads' bursts | " + " | ".join(f"{name}: bursts | p50 | p90" for name in runs) + " |",
             "|---|" + "---|---|---|" * len(runs)]
    rows = [(f"starting {lo}-{hi} ms after a {1e3 * PAUSE_S:.0f}-ms pause", lo, hi)
            for lo, hi in zip(SINCE_PAUSE_MS[:-1], SINCE_PAUSE_MS[1:])] + [("back to back", None, None)]
    for label, lo, hi in rows:
        cells = []
        for after_pause, back_to_back in runs.values():
            if lo is None:
                r = np.asarray(back_to_back)
            else:
                since = np.array([s for s, _ in after_pause])
                r = np.array([x for _, x in after_pause])[(since >= lo) & (since < hi)]
            cells.append(f"{r.size} | {np.median(r):.2f} | {np.percentile(r, 90):.2f}" if r.size else "0 | – | –")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    torch.set_num_threads(args.threads)
    views, keypoints = (int(x) for x in args.config.lower().split("x"))
    problem = rig_window(views, keypoints)
    solver, state = solvers.create(args.solver), StreamState()
    cpus = solve_cpus(args.cpu_affinity)
    pinned = f"solve threads pinned to CPUs {cpus[0]}, {cpus[1]}"
    modes = [("back to back", 0.0, 0.0, False), ("10 Hz, idle between windows", PERIOD_S, 0.0, False)]
    modes += [(f"10 Hz, spin {ms:g} ms before each window", PERIOD_S, ms * 1e-3, False) for ms in args.spin_ms]
    modes += [(f"back to back, {pinned}", 0.0, 0.0, True), (f"10 Hz, idle, {pinned}", PERIOD_S, 0.0, True)]
    speed_before = python_speed()
    t0 = time.monotonic()
    stamp = 0
    for _ in range(4):  # warm-up: model, first fits, first landmarks
        solve_window(solver, problem, state, stamp)
        stamp += 10**8
    times = {name: [] for name, *_ in modes}
    cpu = {name: [] for name, *_ in modes}
    for r in range(args.rounds):
        for name, pace, spin, pin in (modes if r % 2 == 0 else modes[::-1]):
            with _placed(pin, args.cpu_affinity):
                got, got_cpu, stamp = timed_windows(solver, problem, state, args.windows, stamp, pace, spin)
            times[name] += got
            cpu[name] += got_cpu
        print(f"  round {r + 1}/{args.rounds}", flush=True)
    print("  machine check: two threads' bursts", flush=True)
    steps, alone = burst_steps(args.burst_ms * 1e-3)
    bursts = {"placed by the OS": two_thread_bursts(steps, alone, args.pauses),
              f"pinned to CPUs {cpus[0]}, {cpus[1]}": two_thread_bursts(steps, alone, args.pauses, cpus)}
    seconds = time.monotonic() - t0
    base = np.median(times["back to back"])
    lines = ["| mode | windows | p50 [ms] | p90 [ms] | p95 [ms] | max [ms] | slow windows (> "
             f"{SLOW:g}x back-to-back p50) | CPU time p50 [ms] | extra CPU [cores] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, pace, spin, _ in modes:
        t = 1e3 * np.asarray(times[name])
        lines.append(f"| {name} | {t.size} | {np.median(t):.1f} | {np.percentile(t, 90):.1f} | "
                     f"{np.percentile(t, 95):.1f} | {t.max():.1f} | {np.mean(t > 1e3 * SLOW * base):.0%} | "
                     f"{1e3 * np.median(cpu[name]):.1f} | {spin / pace if pace else 0:.2f} |")
    header = results_header("Idling between windows: solve time back to back and at 10 Hz", __file__,
                            argv, torch_threads=args.threads,
                            env=("OPENBLAS_NUM_THREADS",))
    text = ("\n".join(header) + f"\n\n{run_note(seconds, speed_before)}\n\n"
            f"{views} x {keypoints} (synthetic.rome16k, the same window each time, one StreamState, landmarks "
            f"on: solve_window's wall time; CPU time: the process's, both threads, spinning excluded), solver "
            f"`{solver.describe()}`; {args.rounds} rounds of {args.windows} windows a mode, the modes' order "
            f"reversed every other round.\n\n" + "\n".join(lines)
            + f"\n\nThe machine without the matcher: two threads each running a {1e3 * alone:.2f}-ms burst of a "
            f"compiled loop at once, one burst after another over {1e3 * PAUSE_S:.0f} ms after each of "
            f"{args.pauses} pauses, and back to back; wall time of the pair against one burst alone (1.0: a core "
            "each; 2.0: one core shared).\n\n" + "\n".join(burst_table(bursts)) + "\n")
    print(text)
    write_results(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
