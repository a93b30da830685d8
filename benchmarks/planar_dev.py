#!/usr/bin/env python
"""Planar dev windows: homography sequences made from the training scenes' photographs.

The held-out Oxford scenes are the only real planar windows the project scores, so a rule for
planar windows (the one-plane threshold, the H-vs-F model selection) had no dev set of its own.
This makes one: each of the Strecha training images fountain-P11 and entry-P10 0000-0005 (images
< 6 are training data of both shipped models) becomes a 6-view sequence
(data.homography_sequence, the ORB confirmation protocol's SequenceConfig defaults, seed
[20261127, scene index]) under <data>/homography/<name>, converted as the Oxford scenes are
(ORB and SIFT 500, consecutive windows of 3, 4 and 6 views, labels by the exact homographies).

It reports, per detector, every method's F1 / precision, and a census of the windows' trusted
two-view models (edges.candidates.candidate_edges with the default EdgeConfig, so the H-vs-F
ratio edges.verify.PLANAR_RATIO whatever a model stores, before any chained model): how many
windows have a homography for every view pair (what WindowGeometry.one_plane asks), how many
hold a trusted fundamental matrix — on a plane a degenerate model, F = [e']x H for any epipole
e' — and how many a view pair without a trusted model. Those windows are merged at the
precision-first threshold instead of the planar one.

    OPENBLAS_NUM_THREADS=1 ./run.sh python benchmarks/planar_dev.py        # ~1 min on 2 cores
"""
from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from gcn_match_ros.data.convert import convert
from gcn_match_ros.data.homography_sequence import make_sequence
from gcn_match_ros.data.scenes import DATA_ROOT
from gcn_match_ros.edges.candidates import EdgeConfig, candidate_edges
from gcn_match_ros.edges.verify import MIN_SEEDS
from gcn_match_ros.evaluation import evaluate, format_table
from gcn_match_ros.experiments import results_header, write_results
from gcn_match_ros.problem import Problem, load_problem

REPO = Path(__file__).resolve().parents[1]
#: training images of both shipped models (gcn_match_ros/models/README.md: images < 6)
SOURCES = [("strecha/fountain-P11", k) for k in range(6)] + [("strecha/entry-P10", k) for k in range(6)]
SEED = 20261127
METHODS = "gcn;gcn:threshold=0.3;nn-ransac:guided=true"


def make_sequences(data_root: Path, data: Path) -> list:
    """Write every source photograph's sequence under ``data/homography/<name>`` (kept if there);
    returns the scene ids."""
    scenes = []
    for index, (scene, k) in enumerate(SOURCES):
        name = f"{scene.split('/')[1].split('-')[0]}{k}"
        scenes.append(f"homography/{name}")
        make_sequence(data / "homography" / name, functools.partial(_read, data_root / scene / f"{k:04d}.png"),
                      np.random.default_rng([SEED, index]))
    return scenes


def _read(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SystemExit(f"cannot read {path}")
    return image


def model_census(problem: Problem) -> str:
    """'planar' (every view pair of large-enough views has a trusted homography), 'F' (some
    view pair's trusted model is a fundamental matrix) or 'unverified' (no F, but a view pair
    without a trusted model)."""
    models = candidate_edges(problem, EdgeConfig()).models
    large = problem.view_sizes >= MIN_SEEDS
    kinds = [models.get((a, b)) for a in range(problem.n_views) for b in range(a + 1, problem.n_views)
             if large[a] and large[b]]
    if any(m is not None and not m.planar for m in kinds):
        return "F"
    return "unverified" if any(m is None for m in kinds) else "planar"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("/tmp/real_gcn/planar_dev"))
    ap.add_argument("--data-root", type=Path, default=DATA_ROOT)
    ap.add_argument("--detectors", default="orb,sift")
    ap.add_argument("--methods", default=METHODS, help="solver specs separated by ';'")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "planar_dev.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.time()
    scenes = make_sequences(args.data_root, args.data)
    lines = results_header("Planar dev windows (homography sequences from training photographs)", __file__, argv,
                           torch_threads=1, env=("OPENBLAS_NUM_THREADS",)) + [
        f"{len(scenes)} sequences of 6 views made from fountain-P11 and entry-P10 images 0000-0005 (training "
        "images of both models); 500 keypoints; windows of 3, 4, 6 consecutive views; labels by the exact "
        "homographies (true < 3 px, false > 10 px). Census: each window's trusted two-view models at the "
        "default H-vs-F ratio (edges.verify.PLANAR_RATIO), before chaining (planar: a homography for every view "
        "pair, what one-plane windows need)."]
    for det in args.detectors.split(","):
        folder = args.data / det
        folder.mkdir(parents=True, exist_ok=True)
        if not list(folder.glob("*.npz")):
            convert(args.data, folder, scenes, sizes=(3, 4, 6), detectors=(det,), max_features=500)
        problems = [load_problem(f) for f in sorted(folder.glob("*.npz"))]
        census = {p.name: model_census(p) for p in problems}
        report = evaluate(problems, [m for m in args.methods.split(";") if m], progress=False)
        counts = {k: sum(v == k for v in census.values()) for k in ("planar", "F", "unverified")}
        lines += [f"\n## {det.upper()}: {len(problems)} windows\n",
                  f"Census: every view pair a homography {counts['planar']}, a trusted F {counts['F']}, "
                  f"a view pair without a trusted model (no F) {counts['unverified']}.\n",
                  format_table(report), "",
                  "Mean F1 by census class:", "",
                  "| method | " + " | ".join(f"{k} ({counts[k]})" for k in counts) + " |",
                  "|---|" + "---|" * len(counts)]
        for e in report["methods"].values():
            if e.get("reference"):
                continue
            cells = []
            for k in counts:
                f1 = [e["per_problem"][n]["F1"] for n, c in census.items() if c == k and n in e["per_problem"]]
                cells.append(f"{np.mean(f1):.3f}" if f1 else "–")
            lines.append(f"| {e['describe']} | " + " | ".join(cells) + " |")
        print("\n".join(lines[-8:]), flush=True)
    lines.append(f"\nTotal wall time {time.time() - t0:.0f} s.")
    write_results(args.out, "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
