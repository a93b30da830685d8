"""How far photometric pose-scene labels (data.labels.label_photometric) can be trusted, against
the geometric ones (data.labels.label_poses) and a chance test.

For Strecha windows and both detectors:
- coverage: keypoints labelled (gt != -2) and true pairs under each labeller;
- agreement: of the pairs the geometric labels call true (0.5 px confirmations, ~0.5% / 3%
  chance for SIFT / ORB, benchmarks/results/label_chance.md), how many the photometric labels
  call true, false, or leave unlabelled;
- descriptor distance (ORB): the median Hamming distance (of 256 bits) of the geometric-true
  pairs the photometric labels call false, against that of the ones they call true and of
  random pairs (~125): near-random distances mean the geometric label was the wrong one;
- chance: the window's views after the first two replaced by an unrelated image (Oxford graf
  img1, its keypoints and pixels) under the same poses and depth range: every photometric
  pair labelled true between views 0-1 is then wrong.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gcn_match_ros.data.labels import label_photometric, label_poses, window_depth_range
from gcn_match_ros.data.scenes import read_gray
from gcn_match_ros.detect import extract_features
from gcn_match_ros.experiments import DATA_ROOT, WINDOWS, first_pair_tracks, pose_windows, results_header, write_results
from gcn_match_ros.metrics import count_pairs

REPO = Path(__file__).resolve().parents[1]
SCENES = ("strecha/castle-P19", "strecha/fountain-P11", "strecha/entry-P10")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data-root", default=str(DATA_ROOT))
    ap.add_argument("--features", type=int, default=500)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "photometric_labels_check.md"))
    args = ap.parse_args(argv)
    root = Path(args.data_root)
    fake_img = read_gray(root / "oxford" / "graf" / "img1.png")
    lines = results_header("Photometric pose-scene labels against geometric ones", __file__, argv) + [
        f"{args.features} keypoints per view.\n",
        "| detector | scene | window | labelled kps geo / photo | true pairs geo / photo | geo-true pairs: "
        "photo true / false / unlabelled | chance pairs 0-1 (photo) |", "|---|---|---|---|---|---|---|"]
    hamming = {"agree": [], "contradict": []}
    totals = {}
    t0 = time.time()
    for det in ("sift", "orb"):
        fake_kp = extract_features(fake_img, det, args.features).keypoints.astype(np.float64)
        for name, scene, win, views in pose_windows(root, SCENES, WINDOWS, det, args.features):
            kps = [f.keypoints.astype(np.float64) for f, _ in views]
            desc = np.concatenate([f.descriptors for f, _ in views])
            imgs = [image.astype(np.float32) for _, image in views]
            poses = dict(K=scene.K[win], R=scene.R[win], t=scene.t[win])
            view = np.repeat(np.arange(len(win)), [len(k) for k in kps])
            geo = label_poses(kps, **poses)
            z_range = window_depth_range(kps, track=geo, **poses)
            photo = label_photometric(kps, imgs, image_sizes=scene.image_sizes[win], z_range=z_range, **poses)
            # geometric true pairs, judged by the photometric labels
            gt_true = [(i, j) for tr in np.unique(geo[geo >= 0]) for i in np.flatnonzero(geo == tr)
                       for j in np.flatnonzero(geo == tr) if i < j and view[i] != view[j]]
            said_true = [photo[i] >= 0 and photo[i] == photo[j] for i, j in gt_true]
            said_none = [photo[i] == -2 or photo[j] == -2 for i, j in gt_true]
            agree, unl = sum(said_true), sum(said_none)
            disagree = len(gt_true) - agree - unl
            if det == "orb":
                for (i, j), yes, none in zip(gt_true, said_true, said_none):
                    if not none:
                        hamming["agree" if yes else "contradict"].append(np.abs(desc[i] - desc[j]).sum())
            n_extra = len(win) - 2
            fake = label_photometric(kps[:2] + [fake_kp] * n_extra, imgs[:2] + [fake_img.astype(np.float32)] * n_extra,
                                     image_sizes=np.r_[scene.image_sizes[win[:2]],
                                                       np.tile([fake_img.shape[1], fake_img.shape[0]], (n_extra, 1))],
                                     z_range=z_range, **poses) if z_range else np.full(1, -2)
            chance = first_pair_tracks(fake, len(kps[0]), len(kps[1])) if z_range else 0
            tot = totals.setdefault(det, np.zeros(6, int))
            real01 = first_pair_tracks(photo, len(kps[0]), len(kps[1]))
            tot += [len(gt_true), agree, disagree, unl, chance, real01]
            lines.append(f"| {det} | {name.split('/')[1]} | {'-'.join(map(str, win))} | "
                         f"{np.mean(geo != -2):.2f} / {np.mean(photo != -2):.2f} | "
                         f"{count_pairs(geo, view)[1]} / {count_pairs(photo, view)[1]} | "
                         f"{agree} / {disagree} / {unl} of {len(gt_true)} | {chance} |")
            print(lines[-1], flush=True)
    lines.append("")
    for det, (n, agree, disagree, unl, chance, real01) in totals.items():
        lines.append(f"- {det}: of {n} geometric true pairs, photometric labels call {agree} true, {disagree} false, "
                     f"{unl} unlabelled; chance test {chance} wrong pairs against {real01} real ones between views 0-1")
    for k, v in hamming.items():
        lines.append(f"- orb geometric-true pairs the photometric labels call {'true' if k == 'agree' else 'false'}: "
                     f"median Hamming distance {np.median(v) if v else float('nan'):.0f} of 256 ({len(v)} pairs)")
    lines.append(f"\nWall time {time.time() - t0:.0f} s.")
    print("\n".join(lines[-6:]))
    write_results(args.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
