#!/usr/bin/env python
"""End-to-end latency and sustained throughput of the matcher node over real DDS.

For every (cameras, keypoints per view) configuration this starts the matcher node as its
own process (``python -m gcn_match_ros.ros.matcher_node``, own namespace, this machine
only), publishes synchronised Keypoints frames of every camera at ``--rate`` Hz (all
cameras stamped with the same capture time, SIFT-like 128-D descriptors of a synthetic
3D scene: ``--scene still`` the same ``synthetic.rome16k`` scene every capture, ``moving`` a
generated rig driving through a scene, ``data.rig_sequence``) and receives the MatchWindows in a
subscriber:

- latency = receive time of a window - its newest view stamp (capture -> consumer: DDS in,
  windowing, graph, solver, rounding, packing, DDS out), p50 / p95 / max;
- throughput = windows received per second over the measured interval;
- drops: windows not received (of those sent), windows with fewer views than cameras,
  and the node's own counters from /diagnostics (superseded / stale / errors, frames lost);
- memory: the node process's resident memory when measuring begins and after the last window.

The first ``--warmup`` seconds of each configuration are not measured. Prints a markdown
table and writes it, with the command and the machine, to
``benchmarks/results/node_latency.md``.

Usage::

    ./run.sh python benchmarks/node_latency.py                      # default solver (gcn if its model exists)
    ./run.sh python benchmarks/node_latency.py --solver nn --cameras 4 --keypoints 500 --duration 20
    # without the landmarks' temporal association (benchmarks/node_latency_landmarks.py compares both)
    ./run.sh python benchmarks/node_latency.py --landmarks false --cameras 2 4 --out /tmp/no_landmarks.md
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from gcn_match_ros import solvers
from gcn_match_ros.experiments import (describe_machine, python_speed, resident_memory_mb, results_header,
                                      run_note, write_results)

REPO = Path(__file__).resolve().parents[1]

GOAL = (4, 500, 0.050)  # cameras, keypoints per view, p95 seconds (with no drops at 10 Hz)


def thread_placement(solver: str, cpu_affinity: int) -> str:
    """How the node places the solve's threads, in words, for the results' header."""
    if cpu_affinity >= 0:
        return "the solve's two threads pinned, a CPU each"
    if solvers.create(solver).keeps_threads_apart:
        return "the solve's two threads on two CPUs chosen per window"
    return "the OS places the solve's threads"


def _parser():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--solver", default=None, help="solver spec (default: gcn if its model exists, else nn)")
    p.add_argument("--cameras", type=int, nargs="+", default=[2, 4, 8])
    p.add_argument("--keypoints", type=int, nargs="+", default=[250, 500, 1000], help="keypoints per view")
    p.add_argument("--rate", type=float, default=10.0, help="capture rate, Hz")
    p.add_argument("--duration", type=float, default=12.0, help="measured seconds per configuration")
    p.add_argument("--warmup", type=float, default=2.0, help="seconds published before measuring")
    p.add_argument("--input-qos", default="sensor_data", choices=("sensor_data", "reliable"),
                   help="the node's input_qos parameter (default: the node's default)")
    p.add_argument("--default-shm", action="store_true",
                   help="keep Fast DDS's default 512 KiB shared-memory segment (no gcn_match_ros profile)")
    p.add_argument("--scene", default="still", choices=("still", "moving"),
                   help="still: one synthetic scene every capture (every landmark continues, no motion to fit); "
                        "moving: a generated rig driving through a scene, forth and back")
    p.add_argument("--landmarks", default="true", choices=("true", "false"),
                   help="the node's landmarks parameter (false: no temporal association, to measure its cost)")
    p.add_argument("--cpu-affinity", type=int, default=-1,
                   help="the node's cpu_affinity parameter (default -1: two CPUs chosen per window)")
    p.add_argument("--append", action="store_true", help="append to --out instead of replacing it")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "node_latency.md")
    return p


def default_solver() -> str:
    try:
        from gcn_match_ros.solvers.gcn import DEFAULT_CHECKPOINT
        if Path(DEFAULT_CHECKPOINT).is_file():
            return "gcn"
    except ImportError:
        pass
    return "nn"


def machine_extra() -> list:
    """What the shared machine line lacks here: the system and the load average now."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return [f"{platform.system()} {platform.release()}",
            f"load average at start {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}"]


#: windows of the moving scene's rig path, played forth and back (0.25 m a window: 15 m of a 30 m scene)
MOVING_WINDOWS = 60
SCENES = {"still": "the same still scene every capture: every landmark continues, no motion to fit",
          "moving": f"a rig of the cameras driving through a generated scene, {MOVING_WINDOWS} captures "
                    "played forth and back (data.rig_sequence: 0.25 m and 0.5 degrees a capture; at most the "
                    "keypoints per view of the table, fewer where a camera sees fewer points)"}


def _captures(n_cams: int, n_kp: int, scene: str, seed: int = 0) -> list:
    """Per capture, the Keypoints messages of every camera (at most ``n_kp`` a view); the
    publisher cycles through the captures. ``scene`` "still": one synthetic scene
    (``synthetic.rome16k``, exactly ``n_kp`` a view) every time; "moving": a rig driving through
    a generated scene (``data.rig_sequence``; the first ``n_kp`` of a view's keypoints, fewer
    where a camera sees fewer points), played forth and back so that it never jumps."""
    from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
    from gcn_match_ros.data.synthetic import random_scene_problem, rome16k

    if scene == "still":
        return [_messages(random_scene_problem(rome16k(n_cams, n_points=n_kp), rng=seed), n_kp)]
    # 1500 scene points give ~450 keypoints a view on 2 cameras (landmark_eval's rigs; fewer in a
    # wider rig's outer cameras: at 4 x 500 a view's median is 420)
    cfg = RigSequenceConfig(n_cameras=n_cams, n_windows=MOVING_WINDOWS, n_points=int(1500 * 1.1 * n_kp / 450))
    problems, _, _ = rig_sequence(cfg, rng=seed)
    captures = [_messages(p, n_kp) for p in problems]
    return captures + captures[-2:0:-1]


def detector_scores(gt_track: np.ndarray, seed: int = 0) -> np.ndarray:
    """Detector responses for synthetic keypoints, as a real detector's behave: a scene point's
    strength (uniform in [0, 1), the same in every view) times a view's own factor (0.8-1.2), so
    that a frame cut to its best-scored keypoints (the node's ``max_keypoints``, its keypoint budget
    under load) keeps mostly points the other views keep too. Keypoints of no scene point
    (``gt_track`` < 0) score uniformly. Without scores the node keeps the first rows, a random
    subset of each view here: cut to 576 of 1000 keypoints, no camera pair kept a trusted model.

    Shapes: gt_track (N,) int64 -> (N,) float32.
    """
    rng = np.random.default_rng([seed, 7])
    points = gt_track >= 0
    strength = rng.random(int(gt_track.max()) + 1 if points.any() else 0)
    scores = rng.random(gt_track.shape[0])
    scores[points] = strength[gt_track[points]] * rng.uniform(0.8, 1.2, int(points.sum()))
    return scores.astype(np.float32)


def _messages(p, n_kp: int) -> list:
    """Keypoints messages (one per view, camera ids cam0, cam1, ...) of a problem's first ``n_kp``
    keypoints of every view, with detector-like scores (:func:`detector_scores`)."""
    from gcn_match_ros.ros.conversions import frame_to_keypoints
    from gcn_match_ros.windowing import Frame

    scores = detector_scores(p.gt_track)
    msgs = []
    for v in range(p.n_views):
        s = p.view_slice(v)
        idx = np.arange(s.start, s.stop)[:n_kp]
        f = Frame(camera_id=f"cam{v}", stamp_ns=10**9, keypoints=p.keypoints[idx], descriptors=p.descriptors[idx],
                  frame_id=f"cam{v}_optical_frame",
                  scales=None if p.scales is None else p.scales[idx],
                  orientations=None if p.orientations is None else p.orientations[idx],
                  scores=scores[idx], K=p.K[v], image_size=tuple(int(x) for x in p.image_size[v]),
                  descriptor_name="sift")
        msgs.append(frame_to_keypoints(f))
    return msgs


def max_keypoints(n_kp: int) -> int:
    """The node's ``max_keypoints`` in a run of ``n_kp`` keypoints per view: every keypoint, and
    never below the node's default (so degrading under load starts from the same budget)."""
    return max(n_kp, 1024)


def run_config(n_cams, n_kp, args, solver, env, domain) -> dict:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.signals import SignalHandlerOptions

    from gcn_match_msgs.msg import Keypoints, MatchWindow
    from gcn_match_ros.ros.spin import stop_node_process

    ns = f"/bench{n_cams}x{n_kp}"
    cams = [f"cam{v}" for v in range(n_cams)]
    cmd = [sys.executable, "-m", "gcn_match_ros.ros.matcher_node", "--ros-args", "-r", f"__ns:={ns}",
           "-p", f"cameras:=[{','.join(cams)}]", "-p", f"solver:={solver}", "-p", f"input_qos:={args.input_qos}",
           "-p", f"max_keypoints:={max_keypoints(n_kp)}", "-p", "diagnostics_period:=0.5",
           "-p", f"landmarks:={args.landmarks}", "-p", f"cpu_affinity:={args.cpu_affinity}",
           "--log-level", "warn"]
    log = tempfile.NamedTemporaryFile("w+", prefix="node_latency-", suffix=".log", delete=False)
    node_proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
    captures = _captures(n_cams, n_kp, args.scene)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    reliable = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
    node = rclpy.create_node("bench", context=ctx, namespace=ns)
    received = []  # (receive time ns, newest stamp ns, views, node total_seconds)
    diag = {}

    def on_window(m):
        t = time.time_ns()
        received.append((t, m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, len(m.camera_ids),
                         m.total_seconds))

    reports = [0]

    def on_diag(m):
        for st in m.status:
            if st.hardware_id == f"{ns}/matcher_node":
                diag.clear()
                diag.update({kv.key: kv.value for kv in st.values})
                reports[0] += 1

    node.create_subscription(MatchWindow, "matcher_node/matches", on_window, reliable)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, reliable)
    pubs = [node.create_publisher(Keypoints, f"{c}/keypoints", reliable) for c in cams]
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    result = {"cameras": n_cams, "keypoints": n_kp}
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and node_proc.poll() is None and not (
                all(p.get_subscription_count() > 0 for p in pubs)
                and node.count_publishers(f"{ns}/matcher_node/matches") > 0):
            time.sleep(0.02)
        if node_proc.poll() is not None or time.monotonic() >= deadline:
            log.seek(0)
            raise RuntimeError(f"matcher node did not start:\n{log.read()[-2000:]}")
        period = 1.0 / args.rate
        n_ticks = int(round((args.warmup + args.duration) * args.rate))
        measure_from = int(round(args.warmup * args.rate))
        t_next = time.monotonic() + period
        sent_stamps = []
        for k in range(n_ticks):
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)  # the capture clock of the simulated rig
            t_next += period
            now = time.time_ns()
            sec, nsec = divmod(now, 1_000_000_000)
            for m, pub in zip(captures[k % len(captures)], pubs):
                m.header.stamp.sec, m.header.stamp.nanosec = sec, nsec
                pub.publish(m)
            if k == measure_from:
                rss_start = resident_memory_mb(node_proc.pid)
            if k >= measure_from:
                sent_stamps.append(now)
        # Let the last windows arrive, then take the node's counters from a report after them.
        end = time.monotonic() + 5.0
        while time.monotonic() < end and (not received or received[-1][1] < sent_stamps[-1]):
            time.sleep(0.01)
        reports_then = reports[0]
        end = time.monotonic() + 3.0
        while time.monotonic() < end and reports[0] < reports_then + 2:
            time.sleep(0.01)
        diag_end = dict(diag)
        rss_end = resident_memory_mb(node_proc.pid)
    finally:
        stop_node_process(node_proc, timeout=20)
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        spinner.join(2)
        log.close()
        os.unlink(log.name)

    first = sent_stamps[0]
    measured = [r for r in received if r[1] >= first]
    stamps = {r[1] for r in measured}
    lat = np.array([(r[0] - r[1]) * 1e-9 for r in measured])
    comp = np.array([r[3] for r in measured])
    span = (sent_stamps[-1] - sent_stamps[0]) * 1e-9 + 1.0 / args.rate
    windows_dropped = {k[len("windows dropped "):]: int(v) for k, v in diag_end.items()
                       if k.startswith("windows dropped ") and k != "windows dropped total" and v != "0"}
    frames_dropped = {k[len("frames dropped "):]: int(v) for k, v in diag_end.items()
                      if k.startswith("frames dropped ") and k != "frames dropped total" and v != "0"}
    frames_in = sum(int(diag_end.get(f"frames received {c}", 0)) for c in cams)
    frames_sent = n_ticks * n_cams
    result.update(
        sent=len(sent_stamps), received=len(stamps), partial=sum(1 for r in measured if r[2] < n_cams),
        missing=len(sent_stamps) - len(stamps & set(sent_stamps)),
        p50=float(np.percentile(lat, 50)) if lat.size else float("nan"),
        p95=float(np.percentile(lat, 95)) if lat.size else float("nan"),
        max=float(lat.max()) if lat.size else float("nan"),
        compute=float(np.median(comp)) if comp.size else float("nan"),
        throughput=len(stamps) / span, windows_dropped=windows_dropped, frames_dropped=frames_dropped,
        frames_lost=max(0, frames_sent - frames_in) if diag_end else None,
        budget=diag_end.get("keypoint budget", "?"), degraded=diag_end.get("windows degraded", "?"),
        association=float(diag_end.get("landmark association p50 [ms]", "nan")) * 1e-3,
        rss_start=rss_start, rss_end=rss_end)
    return result


def _fmt_ms(seconds: float) -> str:
    return "–" if not np.isfinite(seconds) else f"{1e3 * seconds:.1f}"


def _fmt_drops(d: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items())) or "0"


def ros_environment(args):
    """The environment of the node processes and of this one (this machine only, a domain of its
    own, the large shared-memory segment unless ``args.default_shm``); sets this process's too.

    Returns:
        (env, domain id, a line naming the Fast DDS set-up).
    """
    from gcn_match_ros.ros.dds import FASTDDS_PROFILE_ENV, local_session_env

    env, domain = local_session_env("node_latency-roslog-", large_shm=not args.default_shm)
    shm = ("Fast DDS profile " + env[FASTDDS_PROFILE_ENV]) if env.get(FASTDDS_PROFILE_ENV) else \
        "Fast DDS defaults (512 KiB shared-memory segment)"
    return env, domain, shm


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    solver = args.solver or default_solver()
    env, domain, shm = ros_environment(args)
    import torch

    extra = machine_extra()
    print(f"machine: {describe_machine(torch.get_num_threads(), extra)}", flush=True)
    note = "" if args.solver or solver == "gcn" else " (gcn model not found: fell back to nn)"
    print(f"solver: {solver}{note}; {args.rate:g} Hz, {args.duration:g} s measured per configuration, "
          f"input_qos {args.input_qos}; {shm}", flush=True)
    rows = []
    speed_before = python_speed()
    t0 = time.monotonic()
    for n_cams in args.cameras:
        for n_kp in args.keypoints:
            r = run_config(n_cams, n_kp, args, solver, env, domain)
            rows.append(r)
            print(f"  {n_cams} cameras x {n_kp} keypoints: p50 {1e3 * r['p50']:.1f} ms, p95 {1e3 * r['p95']:.1f} ms, "
                  f"{r['throughput']:.1f} windows/s, {r['received']}/{r['sent']} windows, node drops "
                  f"{_fmt_drops(r['windows_dropped'])}", flush=True)
    header = ("| cameras | keypoints/view | windows received / sent | partial | latency p50 [ms] | p95 [ms] | "
              "max [ms] | node compute p50 [ms] | of it landmark association [ms] | throughput [windows/s] | "
              "windows dropped by the node | frames lost / dropped | keypoint budget at the end / windows degraded | "
              "node RSS, start -> end of measuring [MB] |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [header]
    for r in rows:
        lost = "?" if r["frames_lost"] is None else str(r["frames_lost"])
        lines.append(f"| {r['cameras']} | {r['keypoints']} | {r['received']} / {r['sent']} | {r['partial']} | "
                     f"{1e3 * r['p50']:.1f} | {1e3 * r['p95']:.1f} | {1e3 * r['max']:.1f} | "
                     f"{1e3 * r['compute']:.1f} | {_fmt_ms(r['association'])} | {r['throughput']:.1f} | "
                     f"{_fmt_drops(r['windows_dropped'])} | "
                     f"{lost} / {_fmt_drops(r['frames_dropped'])} | {r['budget']} / {r['degraded']} | "
                     f"{r['rss_start']:.0f} -> {r['rss_end']:.0f} |")
    table = "\n".join(lines)
    goal = [r for r in rows if (r["cameras"], r["keypoints"]) == GOAL[:2]]
    verdict = ""
    if goal:
        g = goal[0]
        ok = g["p95"] < GOAL[2] and g["missing"] == 0 and not g["windows_dropped"]
        verdict = (f"Goal (p95 < {1e3 * GOAL[2]:.0f} ms at {GOAL[0]} cameras x {GOAL[1]} keypoints, no drops at "
                   f"{args.rate:g} Hz): {'MET' if ok else 'NOT MET'} — p95 {1e3 * g['p95']:.1f} ms, "
                   f"{g['missing']} windows missing, node drops {_fmt_drops(g['windows_dropped'])}.")
    seconds = time.monotonic() - t0
    header = results_header("Matcher node: end-to-end latency and throughput", __file__, argv,
                            torch_threads=torch.get_num_threads(), machine_extra=extra)
    doc = "\n".join(header) + f"""
{run_note(seconds, speed_before)}

Solver `{solver}`{note}, landmarks {'on' if args.landmarks == 'true' else 'off'}, node parameter
`cpu_affinity:={args.cpu_affinity}` ({thread_placement(solver, args.cpu_affinity)}); every camera publishes one
Keypoints frame per capture at {args.rate:g} Hz
(all stamped with the capture time; synthetic SIFT-like 128-D descriptors; {SCENES[args.scene]}), {args.duration:g} s measured after
{args.warmup:g} s of warm-up per configuration; the node in its own process, input QoS `{args.input_qos}`,
publishers and the MatchWindow subscriber reliable, all on this machine; {shm}.
Latency = window received by the subscriber − newest view stamp. "partial" = windows with fewer views
than cameras; "windows dropped by the node" = its /diagnostics counters (`superseded`: a newer
window replaced one waiting for the busy worker; `stale_window`); "frames lost" = frames sent
but never received by the node (transport), "dropped" = frames it rejected; "keypoint budget" = the
keypoints per view the node solved at the end of the run (`degrade_min_keypoints`: lowered while
windows are superseded), "windows degraded" = windows it solved below `max_keypoints`; "node RSS" = the
node process's resident memory when the measured captures begin and after the last window. Timings depend on
what else runs: mind the load average above (2 cores shared with other jobs inflate every number).

{table}

{verdict}
"""
    print()
    print(table)
    if verdict:
        print(verdict)
    write_results(args.out, doc, append=args.append)
    return 0


if __name__ == "__main__":
    sys.exit(main())
