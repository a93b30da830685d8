"""A gcn model's scores against its rounding threshold, on the validation sets it can be chosen on.

1. The real validation windows of train_default.py (experiments.split: fountain-P11 / entry-P10,
   images >= 6), scored by their labels. Pose-scene labels confirm few keypoints
   (data/labels.py docstring), and a predicted pair counts only when both keypoints are
   labelled, so the table also gives the share of the predicted pairs that is scored at all:
   where it is small, precision goes unmeasured and F1 favours low thresholds.
2. The same images in the windows of the geometric protocol
   (experiments.geometric_validation_problems: 3-5 views, every 1st or 2nd image), every
   predicted pair scored against the true cameras (geometric_metrics): geometric precision and
   consistent pairs. The threshold is chosen here: the lowest one (most pairs) whose geometric
   precision is at least PRECISION_FLOOR.
3. Generated validation scenes (data/synthetic.py; rome16k and partial, 3 and 4 views, seeds
   training never uses) with descriptors of the model's kind: every keypoint is labelled, so
   false matches always count.

The threshold is a property of the model (stored with it); models/README.md says which set
chose it for each shipped model.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.evaluation import evaluate
from gcn_match_ros.experiments import (DATA_ROOT, SYNTHETIC_DESCRIPTORS, geometric_validation_problems, problem_files,
                                       results_header, split, write_results)
from gcn_match_ros.learn.sources import SYNTH_VAL_SEED
from gcn_match_ros.problem import load_problem
from gcn_match_ros.rounding import tracks_to_pairs

REPO = Path(__file__).resolve().parents[1]
THRESHOLDS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
BASELINE = "nn-ransac:guided=True"
PRECISION_FLOOR = 0.92  # geometric precision the chosen threshold keeps on validation (goal: 0.90)


def generated_validation(descriptor_kind: str, count: int):
    """``count`` generated scenes alternating rome16k / partial and 3 / 4 views."""
    out = []
    for i in range(count):
        config = synthetic.preset(("rome16k", "partial")[i % 2], 3 + (i // 2) % 2, descriptor_kind)
        problem = synthetic.random_scene_problem(config, np.random.default_rng([SYNTH_VAL_SEED, i]))
        problem.name = f"generated-{i:03d}"
        out.append(problem)
    return out


def scored_share(spec: str, problems) -> float:
    """Fraction of the method's predicted pairs whose two keypoints are both labelled."""
    solver = solvers.create(spec)
    total = scored = 0
    for p in problems:
        rows, cols = tracks_to_pairs(solver.solve(p).track)
        labelled = p.gt_track != -2
        total += rows.size
        scored += int(np.sum(labelled[rows] & labelled[cols]))
    return scored / max(total, 1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--detector", choices=tuple(SYNTHETIC_DESCRIPTORS), default="orb")
    ap.add_argument("--checkpoint", default="", help="model to sweep; default: the shipped one of the detector")
    ap.add_argument("--data", default="", help="problem folder (made if empty); default /tmp/real_gcn/train_<detector>")
    ap.add_argument("--data-root", default=str(DATA_ROOT))
    ap.add_argument("--generated", type=int, default=60, help="generated validation scenes")
    ap.add_argument("--out", default="", help="default benchmarks/results/threshold_sweep_<detector>.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    real = [load_problem(f) for f in split(problem_files(args.data, args.data_root, args.detector))[1]]
    posed = geometric_validation_problems(args.data_root, args.detector)
    generated = generated_validation(SYNTHETIC_DESCRIPTORS[args.detector], args.generated)
    pinned = f",checkpoint={args.checkpoint}" if args.checkpoint else ""
    specs = [f"gcn:threshold={t}{pinned}" for t in THRESHOLDS]
    t0 = time.time()
    lines = results_header(f"Rounding threshold sweep ({args.detector})", __file__, argv, torch_threads=1) + [
        f"Model: {args.checkpoint or 'shipped'}; real validation: {len(real)} windows "
        f"({', '.join(p.name for p in real)}); geometric validation: {len(posed)} windows "
        f"({', '.join(p.name for p in posed)}); generated: {len(generated)} scenes "
        f"({SYNTHETIC_DESCRIPTORS[args.detector]} descriptors).\n",
        "| threshold | real val F1 | real val P | scored share of predicted pairs | geometric P | "
        "consistent pairs | generated F1 | generated P | generated R |", "|---|---|---|---|---|---|---|---|---|"]
    rep_real = evaluate(real, specs + [BASELINE], progress=False, with_reference_rows=False)["methods"]
    rep_geo = evaluate(posed, specs + [BASELINE], progress=False, with_reference_rows=False)["methods"]
    rep_gen = evaluate(generated, specs + [BASELINE], progress=False, with_reference_rows=False)["methods"]
    for label, spec in list(zip(THRESHOLDS, specs)) + [(BASELINE, BASELINE)]:
        r, geo, g = rep_real[spec]["mean"], rep_geo[spec]["geometric"], rep_gen[spec]["mean"]
        lines.append(f"| {label} | {r['F1']:.3f} | {r['P']:.3f} | {scored_share(spec, real):.2f} | "
                     f"{geo['precision']:.3f} | {geo['consistent']} | {g['F1']:.3f} | {g['P']:.3f} | {g['R']:.3f} |")
    for label, rep in (("real validation", rep_real), ("generated", rep_gen)):
        best = max(zip(THRESHOLDS, specs), key=lambda ts: (rep[ts[1]]["mean"]["F1"], ts[0]))[0]
        lines.append(f"\nBest threshold by F1 on {label}: {best}")
    floor_met = [t for t, spec in zip(THRESHOLDS, specs) if rep_geo[spec]["geometric"]["precision"] >= PRECISION_FLOOR]
    lines.append(f"\nChosen (lowest threshold with geometric precision >= {PRECISION_FLOOR} on the geometric "
                 f"validation windows): {min(floor_met) if floor_met else 'none reaches it'}")
    lines.append(f"\nWall time {time.time() - t0:.0f} s.")
    out = Path(args.out or REPO / "benchmarks" / "results" / f"threshold_sweep_{args.detector}.md")
    print("\n".join(lines))
    write_results(out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
