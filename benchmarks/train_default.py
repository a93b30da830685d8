"""Train the shipped models gcn_match_ros/models/default.pt (SIFT) and orb.pt (ORB); the exact
commands are in models/README.md.

Data (all made here with data.convert, SIFT or ORB 500, windows of 3, 4 and 6 consecutive views;
the split is gcn_match_ros.experiments: TRAIN_SCENES, SPLIT_AT, split):
- train: Strecha fountain-P11 and entry-P10 windows whose images are all < 6, Middlebury temple;
- validation: fountain-P11 / entry-P10 windows whose images are all >= 6 (the trainer's
  validation loss; their gt labels are used only to compare checkpoints / thresholds by F1);
- never touched: Strecha castle-P19 and all Oxford scenes (held-out test);
- optionally (--synthetic) generated scenes mixed 1:1 into the training stream, with SIFT-like
  or ORB-like binary descriptors to match --detector.
Loss: the project's trainer (learn.train.train) with the paper's L1 reconstruction + epipolar loss
on the embeddings and the edge head's label-free loss (TrainConfig.edge_weight; edges/head.py).
"""
from __future__ import annotations

import argparse
import functools
from pathlib import Path
from typing import Optional

import torch

from gcn_match_ros.data import synthetic
from gcn_match_ros.detect import DETECTOR_KINDS, DETECTORS
from gcn_match_ros.edges.candidates import EDGE_FEATURES
from gcn_match_ros.experiments import DATA_ROOT, SYNTHETIC_DESCRIPTORS, problem_files, split
from gcn_match_ros.graph import GraphConfig
from gcn_match_ros.learn.checkpoint import load_checkpoint, save_checkpoint
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.model import GCNConfig
from gcn_match_ros.learn.sources import InterleavedSource, ProblemFileSource, SyntheticSource
from gcn_match_ros.learn.train import train
from gcn_match_ros.node_features import FeatureConfig, feature_dim
from gcn_match_ros.solvers.gcn import GCNSolverConfig, SHIPPED_MODELS


def synthetic_scene(presets, descriptor_kind, rng):
    """A generated scene (data.synthetic) of a random preset among ``presets``, 3 or 4 views,
    with descriptors of ``descriptor_kind``."""
    name = presets[int(rng.integers(len(presets)))]
    return synthetic.random_scene_problem(synthetic.preset(name, int(rng.integers(3, 5)), descriptor_kind), rng)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--detector", choices=DETECTORS, default="sift")
    ap.add_argument("--data", default="", help="problem folder (made if empty); default /tmp/real_gcn/train_<detector>")
    ap.add_argument("--data-root", default=str(DATA_ROOT))
    ap.add_argument("--out", default="/tmp/real_gcn/run")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--batch-size", type=int, default=2)
    ap.add_argument("--edge-weight", type=float, default=1.0,
                    help="edge head loss weight; 0: no edge head (unless --teacher: then it learns only the "
                         "teacher's scores)")
    ap.add_argument("--epipolar-weight", type=float, default=10.0, help="epipolar loss weight on the embeddings")
    ap.add_argument("--synthetic", default="",
                    help="mix generated scenes 1:1 into the training stream: comma-separated synthetic presets "
                         "(rome16k, partial, easy), 3 or 4 views each, with SIFT-like or (--detector orb) "
                         "ORB-like binary descriptors")
    ap.add_argument("--widths", default="32,32,64,64,64,64", help="output width of each graph layer")
    ap.add_argument("--edge-hidden", type=int, default=64, help="hidden width of the edge head's two layers")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the initial weights, the problem order and the generated scenes (the shipped "
                         "models: 0)")
    ap.add_argument("--teacher", default="",
                    help="checkpoint whose edge scores the edge head also learns (distillation; "
                         "gcn_match_ros/learn/objective.py edge_distillation_loss)")
    ap.add_argument("--distill-weight", type=float, default=1.0,
                    help="weight of the distillation term with --teacher (the shipped default.pt: 16)")
    ap.add_argument("--install", action="store_true",
                    help="copy the result to the shipped model file of its descriptor kind (solvers.gcn.SHIPPED_MODELS)")
    ap.add_argument("--threshold", type=float, default=0.3,
                    help="rounding threshold stored with the model (models/README.md: 0.5 for default.pt and 0.6 "
                         "for orb.pt, chosen on geometric precision)")
    ap.add_argument("--chained-models", choices=("true", "false"), default="false",
                    help="whether gcn fits chained models for view pairs without a trusted one with this model "
                         "(stored with it; models/README.md: true for orb.pt)")
    ap.add_argument("--graph-normalization", choices=("l2", "rootsift"), default=None,
                    help="the descriptor normalization gcn builds this model's graph from at inference (stored "
                         "with it; default: the one already stored with the model, else the one it was trained "
                         "with; models/README.md: rootsift for the shipped models, the candidate edges' own)")
    ap.add_argument("--planar-threshold", type=float, default=None,
                    help="the threshold of windows whose every trusted two-view model is a homography (stored "
                         "with the model; default: the one already stored with it, if any; models/README.md: the "
                         "validation-F1 choices, 0.2 for default.pt and 0.3 for orb.pt)")
    ap.add_argument("--planar-ratio", type=float, default=None,
                    help="the share of F's seeds a homography must explain for a view pair to be planar (stored "
                         "with the model; default: the one already stored with it, if any, else "
                         "edges.verify.PLANAR_RATIO; models/README.md: 0.7 for orb.pt)")
    ap.add_argument("--noise-scaled-residuals", choices=("true", "false"), default=None,
                    help="whether gcn gives this model the residual features of view pairs of noisy keypoints in "
                         "units of their noise (stored with the model; default: the choice already "
                         "stored with it, if any; models/README.md: true for default.pt)")
    ap.add_argument("--restamp", action="store_true",
                    help="only store --threshold, --planar-threshold, --planar-ratio, --chained-models, "
                         "--graph-normalization and --noise-scaled-residuals in the shipped model of --detector "
                         "(weights unchanged; all are chosen after training: models/README.md)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.restamp:
        target = SHIPPED_MODELS[DETECTOR_KINDS[args.detector]]
        _install(target, target, args.threshold, args.chained_models == "true", args.graph_normalization,
                 args.planar_threshold, args.planar_ratio, _flag(args.noise_scaled_residuals))
        return
    train_f, val_f = split(problem_files(args.data, args.data_root, args.detector))
    print(f"train {len(train_f)} problems, validation {len(val_f)}: {[f.stem for f in val_f]}")
    widths = tuple(int(w) for w in args.widths.split(","))
    fc = FeatureConfig()
    kind = DETECTOR_KINDS[args.detector]
    edge_head = args.edge_weight > 0 or bool(args.teacher)
    mc = GCNConfig(in_dim=feature_dim(kind[0], fc), widths=widths, out_dim=32, skip_layers=(len(widths),),
                   edge_features=len(EDGE_FEATURES) if edge_head else 0, edge_hidden=args.edge_hidden, edge_k=4)
    tc = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=1e-3, edge_weight=args.edge_weight,
                     epipolar_weight=args.epipolar_weight, teacher=args.teacher,
                     distill_weight=args.distill_weight if args.teacher else 0.0,
                     val_every=max(args.steps // 4, 1), checkpoint_every=max(args.steps // 4, 1), val_size=len(val_f),
                     graph=GraphConfig(k=4), features=fc, progress=False, plot=False, seed=args.seed)
    source = ProblemFileSource(train_f, seed=args.seed)
    if args.synthetic:
        presets = tuple(args.synthetic.split(","))
        unknown = [p for p in presets if p not in synthetic.PRESETS]
        if unknown:
            raise SystemExit(f"--synthetic: unknown presets {unknown}; choose from {tuple(synthetic.PRESETS)}")
        source = InterleavedSource([source, SyntheticSource(
            functools.partial(synthetic_scene, presets, SYNTHETIC_DESCRIPTORS[args.detector]), seed=args.seed)])
    train(mc, source, ProblemFileSource(val_f, shuffle=False, cycle=False), tc, out_dir=args.out)
    best = Path(args.out) / "checkpoint.pt"
    if args.install:
        _install(best, SHIPPED_MODELS[kind], args.threshold, args.chained_models == "true",
                 args.graph_normalization, args.planar_threshold, args.planar_ratio, _flag(args.noise_scaled_residuals))


def _flag(value: Optional[str]) -> Optional[bool]:
    """A "true" / "false" choice as a bool; None (not given) stays None."""
    return None if value is None else value == "true"


def _install(checkpoint: Path, target: Path, threshold: float, chained_models: bool,
             graph_normalization: Optional[str] = None, planar_threshold: Optional[float] = None,
             planar_ratio: Optional[float] = None, noise_scaled_residuals: Optional[bool] = None) -> None:
    """Write ``checkpoint``'s weights (no optimizer state; models/README.md) with ``threshold``,
    ``chained_models``, ``graph_normalization``, ``planar_threshold``, ``planar_ratio`` and
    ``noise_scaled_residuals`` (None: the one ``checkpoint`` stores, if any) to ``target``
    (atomically: save_checkpoint). A restamp of the threshold alone thus keeps the shipped models'
    other choices."""
    model, meta = load_checkpoint(checkpoint)
    stored = meta["config"].get("solver") or {}
    solver = {"threshold": threshold, "chained_models": chained_models}
    for name, value in (("graph_normalization", graph_normalization), ("planar_threshold", planar_threshold),
                        ("planar_ratio", planar_ratio), ("noise_scaled_residuals", noise_scaled_residuals)):
        value = stored.get(name) if value is None else value
        if value is not None:
            solver[name] = value
    GCNSolverConfig(**solver)  # the solver's own range checks: refuse a setting no solve could use
    save_checkpoint(target, model, dict(meta["config"], solver=solver), {"step": int(meta["extra"].get("step", 0))})
    print("installed", target, "solver settings", solver)


if __name__ == "__main__":
    main()
