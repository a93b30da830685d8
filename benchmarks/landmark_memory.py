#!/usr/bin/env python
"""Bounded landmark state on a long stream: live landmarks and process memory over time.

A 3-camera rig drives for ``--minutes`` at 10 Hz through a corridor of constant point density
(data/rig_sequence.rig_windows, one window made at a time); every window's tracks are the true
ones (points seen by two or more cameras), so this measures the tracker's state and cost alone
(gcn_match_ros.landmarks.LandmarkTracker), not the solver's. Prints one row per simulated
minute: live landmarks, born / retired so far, resident memory, association ms per window.

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/landmark_memory.py --minutes 10   # ~3 min
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_windows
from gcn_match_ros.experiments import resident_memory_mb, results_header, write_results
from gcn_match_ros.landmarks import LandmarkTracker

REPO = Path(__file__).resolve().parents[1]
RATE_HZ = 10


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "landmark_memory.md")
    args = ap.parse_args(argv)
    windows = int(args.minutes * 60 * RATE_HZ)
    base = RigSequenceConfig()
    length = windows * base.step_m + 20.0
    density = 1500 / (base.length_m + 2.0)  # landmark_eval.py's scenes
    cfg = RigSequenceConfig(n_cameras=3, n_windows=windows, n_points=int(density * length), length_m=length,
                            yaw_rate_deg=0.0)
    tracker = LandmarkTracker()
    rows, spent, start = [], [], time.perf_counter()
    for k, (p, truth, stamp) in enumerate(rig_windows(cfg, rng=0)):
        # the true tracks: a point seen by >= 2 cameras of the window
        track = np.where(p.gt_track >= 0, p.gt_track, -1)
        t0 = time.perf_counter()
        tracker.update(p.camera_ids, p.view_offsets, p.keypoints, p.descriptors, track, stamp)
        spent.append(time.perf_counter() - t0)
        if (k + 1) % (60 * RATE_HZ) == 0 or k + 1 == windows:
            rows.append((k + 1, len(tracker), tracker.born, tracker.retired, resident_memory_mb(),
                         1e3 * float(np.median(spent[-600:]))))
            print(f"minute {(k + 1) / 600:.1f}: {len(tracker)} live, {resident_memory_mb():.0f} MB", flush=True)
    lines = ["| stream time [min] | windows | live landmarks | born | retired | RSS [MB] | association [ms/window, median] |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {w / 600:.1f} | {w} | {live} | {born} | {ret} | {rss:.0f} | {ms:.1f} |"
              for w, live, born, ret, rss, ms in rows]
    live = [r[1] for r in rows]
    rss = [r[4] for r in rows]
    verdict = (f"Live landmarks stay within {min(live)}–{max(live)} while {rows[-1][2]} were born; RSS from "
               f"{rss[0]:.0f} to {rss[-1]:.0f} MB after the first minute "
               f"({'flat' if rss[-1] - rss[0] < 0.1 * rss[0] + 20 else 'GROWING'}).")
    header = results_header("Landmark state on a long stream", __file__, argv,
                            env=("OPENBLAS_NUM_THREADS",))
    text = ("\n".join(header) + f"\n\n{cfg.n_cameras} cameras, {RATE_HZ} Hz, {cfg.n_points} scene points along "
            f"{length:.0f} m, true tracks; wall time {time.perf_counter() - start:.0f} s.\n\n"
            + "\n".join(lines) + "\n\n" + verdict + "\n")
    print(text)
    write_results(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
