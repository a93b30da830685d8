#!/usr/bin/env python
"""What the landmarks' temporal association costs the matcher node (issue 13: within 20 %).

For every (cameras, keypoints per view) configuration this runs ``node_latency.run_config``
(the node in its own process, real DDS, synthetic SIFT-like frames at ``--rate`` Hz) with the
node's ``landmarks`` parameter off and on, ``--rounds`` times, alternating which goes first
(off-on, on-off, ...): two separate runs of each differed by more than the association costs
(load and CPU state drift between runs), so each setting is measured on both sides of the other.
Per configuration the table gives the median over rounds of the node's compute p50 and of the
latency p50 / p95, and the ratios on / off of those medians; every round's compute ratio is
listed too. The goal is judged on the compute ratio (the association runs in the node's worker;
latency adds the same transport to both). A configuration whose keypoint budget was lowered
under load in any run is not compared (different windows).

Usage::

    ./run.sh python benchmarks/node_latency_landmarks.py                  # 2 and 4 cameras, 2 rounds
    ./run.sh python benchmarks/node_latency_landmarks.py --cameras 4 --keypoints 500 --rounds 4
    # a moving rig (motion fitted every window), table in node_latency_landmarks_moving.md
    ./run.sh python benchmarks/node_latency_landmarks.py --scene moving --keypoints 500
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import node_latency  # noqa: E402  (the node benchmark this one repeats)

from gcn_match_ros.experiments import (describe_machine, python_speed, results_header, speed_note,  # noqa: E402
                                       write_results)

REPO = Path(__file__).resolve().parents[1]
GOAL_RATIO = 1.20


def _parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--solver", default=None, help="solver spec (default: gcn if its model exists, else nn)")
    p.add_argument("--cameras", type=int, nargs="+", default=[2, 4])
    p.add_argument("--keypoints", type=int, nargs="+", default=[250, 500, 1000], help="keypoints per view")
    p.add_argument("--rounds", type=int, default=2, help="runs of each setting per configuration")
    p.add_argument("--rate", type=float, default=10.0, help="capture rate, Hz")
    p.add_argument("--duration", type=float, default=12.0, help="measured seconds per run")
    p.add_argument("--warmup", type=float, default=2.0, help="seconds published before measuring")
    p.add_argument("--scene", default="still", choices=("still", "moving"), help="as node_latency.py's")
    p.add_argument("--out", type=Path, default=None,
                   help="default: benchmarks/results/node_latency_landmarks.md, _moving.md for the moving scene")
    return p


def _node_args(args, landmarks: bool):
    """node_latency's arguments for one run: its defaults, this run's rate and durations."""
    return node_latency._parser().parse_args(
        ["--rate", str(args.rate), "--duration", str(args.duration), "--warmup", str(args.warmup),
         "--landmarks", "true" if landmarks else "false", "--scene", args.scene])


def compare(n_cams: int, n_kp: int, args, solver: str, env, domain) -> dict:
    """``args.rounds`` runs with the association off and on, alternating which goes first."""
    runs = {False: [], True: []}
    for k in range(args.rounds):
        for landmarks in ((False, True) if k % 2 == 0 else (True, False)):
            r = node_latency.run_config(n_cams, n_kp, _node_args(args, landmarks), solver, env, domain)
            runs[landmarks].append(r)
            print(f"  {n_cams} x {n_kp}, round {k + 1}, landmarks {'on ' if landmarks else 'off'}: compute p50 "
                  f"{1e3 * r['compute']:.1f} ms, latency p50 {1e3 * r['p50']:.1f} / p95 {1e3 * r['p95']:.1f} ms, "
                  f"budget {r['budget']}", flush=True)
    full = str(node_latency.max_keypoints(n_kp))
    med = {on: {q: float(np.median([r[q] for r in runs[on]])) for q in ("compute", "p50", "p95", "association")}
           for on in runs}
    return {"cameras": n_cams, "keypoints": n_kp, "median": med,
            "round_ratios": [a["compute"] / b["compute"] for a, b in zip(runs[True], runs[False])],
            "comparable": all(r["budget"] == full and r["degraded"] == "0" for rs in runs.values() for r in rs),
            "budgets": {on: sorted({r["budget"] for r in runs[on]}) for on in runs}}


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    args.out = args.out or REPO / "benchmarks" / "results" / (
        "node_latency_landmarks.md" if args.scene == "still" else f"node_latency_landmarks_{args.scene}.md")
    solver = args.solver or node_latency.default_solver()
    env, domain, shm = node_latency.ros_environment(_node_args(args, True))
    import torch

    extra = node_latency.machine_extra()
    print(f"machine: {describe_machine(torch.get_num_threads(), extra)}", flush=True)
    speed_before = python_speed()
    t0 = time.monotonic()
    rows = [compare(c, k, args, solver, env, domain) for c in args.cameras for k in args.keypoints]
    seconds = time.monotonic() - t0
    lines = ["| cameras | keypoints/view | node compute p50 on / off [ms] | ratio | per round | "
             "of it landmark association [ms] | within the on runs | latency p50 on / off [ms] | ratio | "
             "p95 on / off [ms] |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    judged = []
    for r in rows:
        on, off = r["median"][True], r["median"][False]
        if r["comparable"]:
            ratio = on["compute"] / off["compute"]
            judged.append((r, ratio))
            ratio_cell, lat_cell = f"{ratio:.2f}", f"{on['p50'] / off['p50']:.2f}"
        else:
            ratio_cell = lat_cell = "– (budget lowered: " + " / ".join(
                ",".join(r["budgets"][s]) for s in (True, False)) + ")"
        within = on["compute"] / (on["compute"] - on["association"])
        lines.append(f"| {r['cameras']} | {r['keypoints']} | {1e3 * on['compute']:.1f} / {1e3 * off['compute']:.1f} | "
                     f"{ratio_cell} | {', '.join(f'{x:.2f}' for x in r['round_ratios'])} | "
                     f"{1e3 * on['association']:.1f} | {within:.2f} | "
                     f"{1e3 * on['p50']:.1f} / {1e3 * off['p50']:.1f} | {lat_cell} | "
                     f"{1e3 * on['p95']:.1f} / {1e3 * off['p95']:.1f} |")
    table = "\n".join(lines)
    worst = max(judged, key=lambda x: x[1]) if judged else None
    verdict = "no configuration comparable" if worst is None else (
        f"Goal (compute ratio <= {GOAL_RATIO:.2f} in every compared configuration): "
        f"{'MET' if worst[1] <= GOAL_RATIO else 'NOT MET'} — worst {worst[1]:.2f} at "
        f"{worst[0]['cameras']} x {worst[0]['keypoints']}.")
    header = results_header("Matcher node: the cost of persistent landmarks (temporal association)", __file__,
                            argv, torch_threads=torch.get_num_threads(), machine_extra=extra)
    doc = "\n".join(header) + f"""
Run {time.strftime('%Y-%m-%d %H:%M')}, {seconds:.0f} s; solver `{solver}`, {args.rate:g} Hz,
{args.duration:g} s measured after {args.warmup:g} s of warm-up per run; {shm}.
{speed_note(speed_before, python_speed())}

Each configuration ran {args.rounds} times with the node's `landmarks` parameter off and
{args.rounds} times on, alternating which went first; the node in its own process, frames as in
node_latency.py ({node_latency.SCENES[args.scene]}).
Medians over the rounds; "ratio" = on / off of those medians (the goal's measure); "per round" =
each round's compute ratio; "of it landmark association" = the association's own time in the
node (its /diagnostics p50 over the last 10 s of each on run), and "within the on runs" = compute
/ (compute - association): the ratio without the run-to-run drift, but also without any
indirect cost. Timings depend on what else runs: mind the load average above.

{table}

{verdict}
"""
    print()
    print(table)
    print(verdict)
    write_results(args.out, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
