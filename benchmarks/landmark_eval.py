#!/usr/bin/env python
"""Persistent landmark ids on generated rig sequences (exact point ids over time).

For 2, 3 and 4 cameras and ``--seeds`` sequences each (data/rig_sequence.py; seed 1 with 3
cameras was used to choose LandmarkConfig's defaults, seeds 10 and 11 were not), every window is solved by the
solver as one stream (rig memory on) and its tracks are given landmark ids by
(a) :class:`gcn_match_ros.landmarks.LandmarkTracker` and (b) the baseline
:class:`gcn_match_ros.landmarks.PerCameraNNLinker` (per-camera mutual nearest neighbours
between consecutive windows). Metrics: gcn_match_ros.landmark_metrics. Goals (issue 13): id
precision >= 0.95 and fragmentation <= 1.2 on these sequences.

Then the sample bags (bags/: Oxford graf and boat replayed as a rig sliding along the
images, Strecha fountain with poses), whose scene-global labels give each keypoint its true
point (unlabelled keypoints count as no point): the same two id assignments on the windows the
matcher node forms on replay, solved as one stream; and the same on real sequences never used
to choose the tracker's settings (``--held-out-scenes``, made into bags like the sample bags).
Where the windows have camera poses, the ids are also scored as a mapping consumer sees them
(:func:`gcn_match_ros.landmark_map.held_out_sighting_errors`): every window is predicted by the
map triangulated from the windows before it — median reprojection error, share within 3 px,
sightings predicted (and how many within 3 px); over all of each method's sightings, over those
both methods predict, and over those only one predicts. The maps compare like for like (on the
sightings both predict) and by the sightings predicted within 3 px (:data:`HIGHER_IS_BETTER`).

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/landmark_eval.py          # ~4 min
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
from gcn_match_ros.experiments import results_header, write_results
from gcn_match_ros.landmark_map import held_out_sighting_errors, reprojection_summary
from gcn_match_ros.landmark_metrics import landmark_scores, true_points
from gcn_match_ros.landmarks import LandmarkTracker, PerCameraNNLinker
from gcn_match_ros.stream import StreamState

REPO = Path(__file__).resolve().parents[1]
METRICS = ("id_precision", "switches_per_100", "fragmentation", "lifetime", "true_span", "landmarks")
#: held_out_sighting_errors: sightings of mapped landmarks predicted by the map of earlier windows
#: (and how many within 3 px); then the same on the sightings both id assignments predict (like
#: for like: a method that keeps landmarks longer also predicts sightings farther from where they
#: were mapped), and on those only this one predicts (what its extra landmarks are worth)
MAP_METRICS = ("median_px", "within_px", "predicted", "predicted_within", "median_px_both", "within_px_both",
               "predicted_both", "median_px_only", "within_px_only", "predicted_only")
#: the comparison with the baseline (:func:`not_better`). A map's accuracy compares like for like,
#: on the sightings both maps predict; statistics over each map's own sightings do not compare two
#: maps that predict different sightings (the one predicting more, of landmarks mapped from fewer
#: sightings, gets a larger median; one predicting nothing, none), so coverage compares by how many
#: sightings each predicts within 3 px.
HIGHER_IS_BETTER = ("id_precision", "lifetime", "within_px_both", "predicted_within")
LOWER_IS_BETTER = ("switches_per_100", "fragmentation", "median_px_both")
#: real sequences never used to choose LandmarkConfig (the sample bags were)
HELD_OUT_SCENES = ("oxford/bikes", "oxford/wall", "strecha/castle-P19", "strecha/entry-P10", "middlebury_temple")


def scores(problems, stamps, ours, base, truth):
    """landmark_scores of both id assignments, and with camera poses the held-out reprojection of
    their maps: over all sightings each predicts, and over those both predict (``*_both``)."""
    out = landmark_scores(ours, truth), landmark_scores(base, truth)
    if all(p.R is not None and p.K is not None for p in problems):
        errors = [held_out_sighting_errors(problems, ids, stamps) for ids in (ours, base)]
        both = errors[0].keys() & errors[1].keys()
        for m, e in zip(out, errors):
            m.update(reprojection_summary(e.values()))
            m.update({f"{k}_both": v for k, v in reprojection_summary([e[k] for k in both]).items()})
            m.update({f"{k}_only": v for k, v in reprojection_summary([e[k] for k in e.keys() - both]).items()})
    return out


def cells(m):
    """The table cells of one row of scores (map metrics '-' without poses)."""
    fmt = {"id_precision": "{:.3f}", "landmarks": "{:.0f}",
           **{f"{k}{part}": f for part in ("", "_both", "_only")
              for k, f in (("median_px", "{:.3f}"), ("within_px", "{:.3f}"), ("predicted", "{:.0f}"),
                         ("predicted_within", "{:.0f}"))}}
    return " | ".join(fmt.get(k, "{:.2f}").format(m[k]) if k in m else "-" for k in METRICS + MAP_METRICS)


def assign_ids(solver_spec: str, problems, stamps):
    """Solve the windows as one stream and give them ids both ways: (tracker ids, baseline ids,
    median solve seconds, median tracker seconds), per window."""
    solver, state, tracker, linker = solvers.create(solver_spec), StreamState(), LandmarkTracker(), PerCameraNNLinker()
    ours, base, solve_s, track_s = [], [], [], []
    for p, ns in zip(problems, stamps):
        result = solver.solve(p, stream=state)
        solve_s.append(result.seconds)
        t0 = time.perf_counter()
        ours.append(tracker.update(p.camera_ids, p.view_offsets, p.keypoints, p.descriptors, result.track, ns)[0])
        track_s.append(time.perf_counter() - t0)
        base.append(linker.update(p.camera_ids, p.view_offsets, p.descriptors, result.track))
    return ours, base, float(np.median(solve_s)), float(np.median(track_s))


def run_sequence(solver_spec: str, cameras: int, seed: int, windows: int):
    problems, truth, stamps = rig_sequence(RigSequenceConfig(n_cameras=cameras, n_windows=windows, n_points=1500),
                                           rng=seed)
    ours, base, solve_s, track_s = assign_ids(solver_spec, problems, stamps)
    return (*scores(problems, stamps, ours, base, truth), solve_s, track_s)


def run_bag(solver_spec: str, path: Path):
    """(tracker scores, baseline scores, windows) on a labelled sample bag."""
    from gcn_match_ros.bags.contents import read_bag

    replay = read_bag(path, progress=False).replay_windows()
    problems, stamps = replay.problems, replay.stamps_ns
    truth = [true_points(labels, p.n_keypoints) for labels, p in zip(replay.labels, problems)]
    ours, base, _, _ = assign_ids(solver_spec, problems, stamps)
    return (*scores(problems, stamps, ours, base, truth), len(problems))


def held_out_bags(scenes, cache: Path):
    """The bags of ``scenes`` (SIFT, 3 cameras, as ``gcn-match make-bags``), made once into ``cache``."""
    from gcn_match_ros.bags.make import bag_name, convert_scene_to_bag
    from gcn_match_ros.data.scenes import DATA_ROOT

    cache.mkdir(parents=True, exist_ok=True)
    out = []
    for scene in scenes:
        path = cache / bag_name(scene, "sift")
        if not path.exists():
            print(f"making {path.name} from {DATA_ROOT / scene}", flush=True)
            convert_scene_to_bag(DATA_ROOT, scene, path, progress=False)
        out.append(path)
    return out


def not_better(ours, base):
    """The metrics (:data:`HIGHER_IS_BETTER`, :data:`LOWER_IS_BETTER`) on which the tracker is
    not better than the baseline."""
    return ([k for k in HIGHER_IS_BETTER if k in ours and ours[k] <= base[k]]
            + [k for k in LOWER_IS_BETTER if k in ours and ours[k] >= base[k]])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--solver", default="gcn")
    ap.add_argument("--cameras", type=int, nargs="+", default=[2, 3, 4])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 10, 11])
    ap.add_argument("--windows", type=int, default=20)
    ap.add_argument("--held-out-scenes", nargs="*", default=list(HELD_OUT_SCENES),
                    help="dataset scenes under ../shared/data made into bags like the sample bags")
    ap.add_argument("--bag-cache", type=Path, default=REPO / "out" / "landmark_eval_bags")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "landmark_eval.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    head = ("| cameras | seed | ids by | " + " | ".join(METRICS + MAP_METRICS) + " | solve [ms/window] | ids [ms/window] |")
    lines = [head, "|" + "---|" * (len(METRICS + MAP_METRICS) + 5)]
    agg = {"tracker": [], "baseline": []}
    overhead = {}  # cameras -> association / solve time per sequence
    for cams in args.cameras:
        for seed in args.seeds:
            ours, base, solve_s, track_s = run_sequence(args.solver, cams, seed, args.windows)
            overhead.setdefault(cams, []).append(track_s / solve_s)
            for name, m, t in (("tracker", ours, track_s), ("baseline (per-camera NN)", base, None)):
                agg["tracker" if name == "tracker" else "baseline"].append(m)
                lines.append(f"| {cams} | {seed} | {name} | {cells(m)} | {1e3 * solve_s:.0f} | "
                             f"{'' if t is None else f'{1e3 * t:.1f}'} |")
            print(f"{cams} cameras, seed {seed}: precision {ours['id_precision']:.3f} / {base['id_precision']:.3f}, "
                  f"fragmentation {ours['fragmentation']:.2f} / {base['fragmentation']:.2f}", flush=True)
    bag_lines = {}
    shortfalls = []
    for section, bags in (("sample", sorted((REPO / "bags").glob("*.mcap"))),
                          ("held-out", held_out_bags(args.held_out_scenes, args.bag_cache))):
        rows = bag_lines.setdefault(section, ["| bag | windows | ids by | " + " | ".join(METRICS + MAP_METRICS) + " |",
                                              "|" + "---|" * (len(METRICS + MAP_METRICS) + 3)])
        for bag in bags:
            ours, base, n = run_bag(args.solver, bag)
            for name, m in (("tracker", ours), ("baseline (per-camera NN)", base)):
                rows.append(f"| {bag.name} | {n} | {name} | {cells(m)} |")
            worse = not_better(ours, base)
            shortfalls.append(f"{bag.name}: " + (f"not better on {', '.join(worse)}" if worse else "better on every metric"))
            print(f"{bag.name}: precision {ours['id_precision']:.3f} / {base['id_precision']:.3f}, fragmentation "
                  f"{ours['fragmentation']:.2f} / {base['fragmentation']:.2f}; {shortfalls[-1]}", flush=True)
    cost = "; ".join(f"{c} cameras {100 * max(v):.0f}%" for c, v in sorted(overhead.items()))
    within = max(max(v) for v in overhead.values()) <= 0.2
    tracker_share = (f"The tracker's time relative to solving the window, both on one thread (worst sequence; "
                     f"its search included, which the node runs beside the solve): {cost} — "
                     f"{'within' if within else 'above'} 20%. A stricter measure than issue 13's goal, the node's "
                     "latency with landmarks within 20% of without, which node_latency_landmarks.py --scene moving "
                     "measures.")
    worst_p = min(m["id_precision"] for m in agg["tracker"])
    worst_f = max(m["fragmentation"] for m in agg["tracker"])
    verdict = (f"Goals (every sequence): id precision >= 0.95: worst {worst_p:.3f}, "
               f"{'met' if worst_p >= 0.95 else 'NOT met'}; fragmentation <= 1.2: worst {worst_f:.2f}, "
               f"{'met' if worst_f <= 1.2 else 'NOT met'}.")
    header = results_header("Persistent landmark ids on generated rig sequences", __file__,
                            argv, torch_threads=1, env=("OPENBLAS_NUM_THREADS",))
    text = "\n".join(header) + (
        f"\n\nSolver `{args.solver}` (one stream per sequence); {args.windows} windows per sequence, 1500 scene "
        "points, SIFT-like descriptors at the calibrated noise; ids by LandmarkTracker (defaults) and by the "
        "baseline on the same tracks. lifetime / true_span: mean windows a landmark lives / a true point is "
        "seen with an id. median_px / within_px / predicted / predicted_within: each window's sightings of "
        "landmarks already mapped from the earlier windows (true camera poses), reprojection error [px], share "
        "within 3 px, how many, how many within 3 px ('-': no poses, the Oxford sequences); *_both: the same over "
        "the sightings that both the tracker's and the baseline's maps predict (like for like: longer-lived "
        "landmarks are also predicted farther from where they were mapped); *_only: over the sightings only this "
        "method's map predicts (its extra landmarks). The maps compare below like for like (*_both) and by "
        "predicted_within; median_px and within_px over each map's own sightings do not compare two maps that "
        "predict different sightings (the one predicting more, of landmarks mapped from fewer sightings, gets a "
        "larger median; a map predicting nothing would get none).\n\n" + "\n".join(lines) + "\n\n" + verdict + "\n\n" + tracker_share
        + "\n\n## Sample bags (real images, labels)\n\n"
        + "\n".join(bag_lines["sample"]) + "\n\n## Held-out real sequences (bags made by `gcn-match make-bags`; "
        "not seen when LandmarkConfig was chosen)\n\n" + "\n".join(bag_lines["held-out"])
        + f"\n\nThe tracker against the baseline, per real sequence ({', '.join(HIGHER_IS_BETTER)}: higher is "
        f"better; {', '.join(LOWER_IS_BETTER)}: lower):\n\n" + "\n".join(f"- {x}" for x in shortfalls)
        + "\n")
    print(text)
    write_results(args.out, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
