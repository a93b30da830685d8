"""How many pose-scene ground-truth pairs are chance confirmations (data.labels.label_poses).

For each Strecha window and detector, the pairs labelled true between the window's first two
views are counted twice: with the real window, and with every other view's keypoints replaced
by those of an unrelated image (Oxford graf img1) under the same poses. In the second case
no confirmation can be right, so its count estimates how many of the real count are chance.
Also printed: the labelled true pairs of the whole window (what the benchmark scores).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gcn_match_ros.data.labels import label_poses
from gcn_match_ros.data.scenes import read_gray
from gcn_match_ros.detect import extract_features
from gcn_match_ros.experiments import DATA_ROOT, WINDOWS, first_pair_tracks, pose_windows, results_header, write_results
from gcn_match_ros.metrics import count_pairs

REPO = Path(__file__).resolve().parents[1]
SCENES = ("strecha/fountain-P11", "strecha/entry-P10", "strecha/castle-P19")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-root", default=str(DATA_ROOT))
    ap.add_argument("--features", type=int, default=500, help="keypoints per view (the benchmark's 500)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "label_chance.md"))
    args = ap.parse_args(argv)
    root = Path(args.data_root)
    unrelated = read_gray(root / "oxford" / "graf" / "img1.png")
    lines = results_header("Chance confirmations in pose-scene labels", __file__, argv) + [
        f"{args.features} keypoints per view; label_poses at its defaults (0.5 px).\n",
        "| detector | scene | window | true pairs views 0-1 | of which chance (estimate) | "
        "true pairs, whole window |", "|---|---|---|---|---|---|"]
    totals = {}
    t0 = time.time()
    for det in ("sift", "orb"):
        fake = extract_features(unrelated, det, args.features).keypoints
        for name, scene, win, views in pose_windows(root, SCENES, WINDOWS, det, args.features):
            kps = [f.keypoints for f, _ in views]
            poses = dict(K=scene.K[win], R=scene.R[win], t=scene.t[win])
            n0, n1 = len(kps[0]), len(kps[1])
            gt = label_poses(kps, **poses)
            real = first_pair_tracks(gt, n0, n1)
            chance = first_pair_tracks(label_poses(kps[:2] + [fake] * (len(win) - 2), **poses), n0, n1)
            view = np.repeat(np.arange(len(win)), [len(k) for k in kps])
            whole = count_pairs(gt, view)[1]
            tot = totals.setdefault(det, [0, 0])
            tot[0] += real
            tot[1] += chance
            lines.append(f"| {det} | {name.split('/')[1]} | {'-'.join(map(str, win))} | {real} | {chance} | "
                         f"{whole} |")
    lines.append("")
    for det, (real, chance) in totals.items():
        lines.append(f"- {det}: {chance} chance of {real} labelled pairs between views 0-1 "
                     f"({100 * chance / max(real, 1):.1f}%)")
    lines.append(f"\nWall time {time.time() - t0:.0f} s.")
    print("\n".join(lines))
    write_results(args.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
