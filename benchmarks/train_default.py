"""Train the shipped model gcn_match_ros/models/default.pt (the exact command is in models/README.md).

Data (all made here with datasets.convert, SIFT 500, windows of 3, 4 and 6 consecutive views):
- train: Strecha fountain-P11 and entry-P10 windows whose images are all < 6, Middlebury temple;
- validation: fountain-P11 / entry-P10 windows whose images are all >= 6 (the trainer's
  validation loss; their gt labels are used only to compare checkpoints / thresholds by F1);
- never touched: Strecha castle-P19 and all Oxford scenes (held-out test).
Loss: the project's trainer (train.train) with the paper's L1 reconstruction + epipolar loss on
the embeddings and the edge head's label-free loss (TrainConfig.edge_weight; edge_head.py).
"""
from __future__ import annotations

import argparse
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gcn_match_ros.datasets import convert  # noqa: E402
from gcn_match_ros.edge_features import EDGE_FEATURES  # noqa: E402
from gcn_match_ros.features import FeatureConfig, feature_dim  # noqa: E402
from gcn_match_ros.graph import GraphConfig  # noqa: E402
from gcn_match_ros.model import GCNConfig  # noqa: E402
from gcn_match_ros.train import ProblemFileSource, TrainConfig, train  # noqa: E402

TRAIN_SCENES = ["strecha/fountain-P11", "strecha/entry-P10", "middlebury_temple"]
SPLIT_AT = 6  # Strecha windows with every image < SPLIT_AT train, every image >= SPLIT_AT validate


def images_of(name: str):
    tail = name.rsplit("_", 1)[1]
    return [int(x) for x in (tail.split("-") if "-" in tail else list(tail))]


def split(files):
    train_f, val_f = [], []
    for f in files:
        if "castle" in f.name or f.name.startswith("oxford"):
            continue  # held-out test scenes: never used
        if f.name.startswith("strecha"):
            ims = images_of(f.stem)
            if max(ims) < SPLIT_AT:
                train_f.append(f)
            elif min(ims) >= SPLIT_AT:
                val_f.append(f)
        else:
            train_f.append(f)
    return train_f, val_f


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", default="/tmp/real_gcn/sift", help="problem folder (made if empty)")
    ap.add_argument("--data-root", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--out", default="/tmp/real_gcn/run")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--edge-weight", type=float, default=1.0)
    ap.add_argument("--widths", default="32,32,64,64,64,64")
    ap.add_argument("--install", action="store_true", help="copy the result to gcn_match_ros/models/default.pt")
    ap.add_argument("--threshold", type=float, default=0.3,
                    help="rounding threshold stored with the model (chosen by validation F1 among "
                         "0.1, 0.2, ..., 0.7; see models/README.md)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    data = Path(args.data)
    if not list(data.glob("*.npz")):
        convert(Path(args.data_root), data, TRAIN_SCENES, sizes=(3, 4, 6), detectors=("sift",), max_features=500)
    train_f, val_f = split(sorted(data.glob("*.npz")))
    print(f"train {len(train_f)} problems, validation {len(val_f)}: {[f.stem for f in val_f]}")
    widths = tuple(int(w) for w in args.widths.split(","))
    fc = FeatureConfig()
    mc = GCNConfig(in_dim=feature_dim(128, fc), widths=widths, out_dim=32, skip_layers=(len(widths),),
                   edge_features=len(EDGE_FEATURES), edge_hidden=64, edge_k=4)
    tc = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=1e-3, edge_weight=args.edge_weight,
                     val_every=max(args.steps // 4, 1), checkpoint_every=max(args.steps // 4, 1), val_size=len(val_f),
                     graph=GraphConfig(k=4), features=fc, progress=False, plot=False, seed=0)
    train(mc, ProblemFileSource(train_f, seed=0), ProblemFileSource(val_f, shuffle=False, cycle=False), tc,
          out_dir=args.out)
    best = Path(args.out) / "checkpoint.pt"
    if args.install:
        # the final weights, saved without optimizer state (see models/README.md)
        from gcn_match_ros.model import load_checkpoint, save_checkpoint
        model, meta = load_checkpoint(best)
        config = dict(meta["config"], solver={"threshold": args.threshold})
        save_checkpoint(ROOT / "gcn_match_ros" / "models" / "default.pt", model, config,
                        {"step": int(meta["extra"].get("step", 0))})
        print("installed", ROOT / "gcn_match_ros" / "models" / "default.pt")


if __name__ == "__main__":
    main()
