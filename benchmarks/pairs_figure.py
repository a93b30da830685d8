"""A picture of one view pair's predicted pairs, each coloured by the true cameras: green =
geometrically consistent (benchmarks/geometric_eval.py's test), red = not; one row per method.

Made to see what a rule changes where it matters, e.g. castle-P19's facade, where matches
shifted by one window keep the epipolar geometry (the neighbourhood rule, edges/neighbourhood.py):

    ./run.sh python benchmarks/pairs_figure.py --scene strecha/castle-P19 --window 13 14 15 16 17 18 \\
        --views 13 14 --methods gcn:neighbours=0 gcn --out benchmarks/results/castle_pairs.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.data.convert import make_problem
from gcn_match_ros.data.scenes import load_scene
from gcn_match_ros.experiments import DATA_ROOT
from gcn_match_ros.geometric_metrics import score_geometric

RIGHT, WRONG = (60, 200, 60), (40, 40, 230)  # BGR
WIDTH = 1600  # of each row, pixels


def _row(scene, problem, method: str, window, views, images):
    """The two images side by side with ``method``'s pairs between ``views`` drawn, and a caption."""
    result = solvers.create(method).solve(problem)
    g = score_geometric(problem, result, view_numbers=[int(scene.view_labels[v]) for v in window])
    a, b = (window.index(v) for v in views)
    va, vb = problem.view_index[g.rows], problem.view_index[g.cols]
    pick = np.flatnonzero(((va == a) & (vb == b)) | ((va == b) & (vb == a)))
    canvas = np.concatenate([cv2.cvtColor(im, cv2.COLOR_GRAY2BGR) for im in images], axis=1)
    shift = np.array([images[0].shape[1], 0.0])
    for i in pick:
        pa, pb = problem.keypoints[g.rows[i]], problem.keypoints[g.cols[i]]
        if va[i] != a:
            pa, pb = pb, pa
        colour = RIGHT if g.consistent[i] else WRONG
        ends = [tuple(int(round(c)) for c in p) for p in (pa, pb + shift)]
        cv2.line(canvas, ends[0], ends[1], colour, 1, cv2.LINE_AA)
        for e in ends:
            cv2.circle(canvas, e, 3, colour, 1, cv2.LINE_AA)
    scale = WIDTH / canvas.shape[1]
    canvas = cv2.resize(canvas, (WIDTH, int(round(canvas.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    wrong = int((~g.consistent[pick]).sum())
    caption = f"{method}: {pick.size} pairs, {wrong} not consistent with the true cameras (red)"
    bar = np.full((36, WIDTH, 3), 255, np.uint8)
    cv2.putText(bar, caption, (10, 25), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 1, cv2.LINE_AA)
    print(caption, flush=True)
    return np.concatenate([bar, canvas], axis=0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="strecha/castle-P19")
    ap.add_argument("--window", type=int, nargs="+", default=[13, 14, 15, 16, 17, 18], help="image indices")
    ap.add_argument("--views", type=int, nargs=2, default=[13, 14], help="the two images drawn (in the window)")
    ap.add_argument("--methods", nargs="+", default=["gcn:neighbours=0", "gcn"])
    ap.add_argument("--detector", default="sift", choices=("sift", "orb"))
    ap.add_argument("--features", type=int, default=500)
    ap.add_argument("--data-root", default=str(DATA_ROOT))
    ap.add_argument("--out", type=Path, default=Path("out") / "pairs_figure.png")
    args = ap.parse_args(argv)
    if not set(args.views) <= set(args.window) or args.views[0] == args.views[1]:
        ap.error("--views must be two different images of --window")
    torch.set_num_threads(1)
    scene = load_scene(Path(args.data_root), args.scene)
    window = list(args.window)
    problem = make_problem(scene, tuple(window), args.detector, args.features, {})
    images = [cv2.imread(str(scene.image_paths[v]), cv2.IMREAD_GRAYSCALE) for v in args.views]
    if any(im is None for im in images):
        raise SystemExit(f"cannot read the images of views {args.views}")
    # the images as the problem's keypoints see them (make_problem may work on resized images)
    h, w = images[0].shape
    span = problem.keypoints.max(axis=0)
    if span[0] > w or span[1] > h:
        raise SystemExit("keypoints outside the images: the detector's images differ from the files")
    rows = [_row(scene, problem, m, window, list(args.views), images) for m in args.methods]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), np.concatenate(rows, axis=0))
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
