"""``gcn-match``: every offline command of the project.

    gcn-match synth -o DIR [--preset rome16k|partial|easy] [--views 3] [--descriptor sift|gaussian|binary]
                    [--count 10] [--seed 0]
    gcn-match convert --scenes oxford/graf strecha/fountain-P11 -o DIR   (real images -> problems)
    gcn-match match PROBLEM.npz --method gcn -o RESULT.npz
    gcn-match eval PROBLEM.npz... --methods nn,gcn,matchals [--json OUT] [--pr-plot PNG]
    gcn-match train --train DATA... --val DATA... -o RUN_DIR [--steps N] [--resume]
    gcn-match plot RUN_DIR... -o curves.png [--data DATA... --pr PNG --similarity PNG --histograms PNG]
    gcn-match make-bags --out bags/ [--scenes ...] [--detector sift|orb] [--cameras 3]
    gcn-match stream BAG [--method gcn] [--window max_keypoints=500 ...] [-o DIR]   (a bag as the node sees it)

``torchrun --nproc_per_node=N -m gcn_match_ros.cli train ...`` trains data-parallel
(:mod:`gcn_match_ros.learn.ddp`). Every failure caused by arguments or input files prints
one line (``gcn-match: error: ...``) and exits with status 2; no traceback
(``GCN_MATCH_DEBUG=1`` shows it).
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import shutil
import sys
from itertools import islice
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from . import evaluation, plots, solvers
from .bags import make as bag_make
from .bags.contents import read_bag, window_labels
from .bags.io import STORAGES, bag_info
from .bags.typesys import KEYPOINTS_TYPE
from .data import synthetic
from .data.convert import convert
from .data.scenes import DATA_ROOT, DatasetError
from .landmark_metrics import landmark_scores, true_points
from .graph import CorrespondenceGraph, GraphConfig
from .learn import ddp
from .learn.checkpoint import load_checkpoint
from .learn.config import TrainConfig
from .learn.model import GCN, GCNConfig, embed_problem
from .learn.sources import DataSource, check_disjoint, data_source
from .learn.train import train
from .node_features import FeatureConfig, feature_dim
from .problem import Problem, load_problem, save_problem, save_result
from .stream import StreamState, solve_stream
from .threads import single_blas_thread
from .windowing import WindowConfig, window_parameters

__all__ = ["main", "build_parser"]



class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line instead of usage + error
        raise _UserError(f"{message} (see '{self.prog} --help')")


class _UserError(Exception):
    """A problem with the user's arguments or files: reported in one line."""


def _expand(patterns: Sequence[str]) -> List[Path]:
    paths: List[Path] = []
    for pat in patterns:
        hits = sorted(glob.glob(pat)) if any(ch in pat for ch in "*?[") else [pat]
        if not hits:
            raise _UserError(f"no file matches '{pat}'")
        paths.extend(Path(h) for h in hits)
    return paths


def _embed(loaded: Tuple[GCN, Dict[str, Any]], problem: Problem) -> Tuple[np.ndarray, CorrespondenceGraph]:
    """(embeddings, graph) of ``problem`` by a loaded checkpoint, with the settings it was trained with."""
    model, meta = loaded
    return embed_problem(model, problem, meta["graph_config"], meta["feature_config"])


def _first_problem(source: DataSource, what: str) -> Problem:
    try:
        return next(iter(source(0)))
    except StopIteration:
        raise ValueError(f"{what} data yields no problems") from None


# -- subcommands ---------------------------------------------------------------
def _cmd_synth(args) -> int:
    config = synthetic.preset(args.preset, args.views, args.descriptor)
    paths = synthetic.write_problems(args.out, lambda rng: synthetic.random_scene_problem(config, rng),
                                     count=args.count, seed=args.seed, prefix=args.prefix)
    print(f"wrote {len(paths)} problems to {args.out}")
    return 0


def _cmd_match(args) -> int:
    problem = load_problem(args.problem)
    result = solvers.create(args.method).solve(problem)
    save_result(result, args.output)
    n_tracks = int(result.track.max(initial=-1)) + 1
    print(f"{problem.name}: {result.method}: {n_tracks} tracks, {result.pair_rows.size} scored pairs, "
          f"{result.seconds * 1e3:.1f} ms -> {args.output}")
    return 0


def _cmd_eval(args) -> int:
    problems = _expand(args.problems)
    methods = solvers.parse_method_list(args.methods)
    report = evaluation.evaluate(problems, methods, progress=not args.quiet)
    print(evaluation.format_table(report))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    if args.pr_plot:
        plots.plot_pr_curves(report, args.pr_plot)
    return 0


def _cmd_train(args) -> int:
    """``gcn-match train``: build the sources, configurations and run :func:`learn.train.train`.

    Started by torchrun, every process is one rank of a distributed run (:mod:`learn.ddp`). The model
    configuration is, in order: ``--model-config`` JSON (``in_dim`` filled in when missing),
    the run's own ``checkpoint.pt`` when resuming, the ``--init`` checkpoint, else the
    defaults with ``in_dim = feature_dim(D)``; graph and feature settings come from the
    resumed / ``--init`` checkpoint (else defaults). After training, rank 0 prints where
    the checkpoints and plots are and draws, when the validation data has ground truth,
    the similarity matrix and histograms of the best model.

    Raises:
        ValueError / OSError: bad arguments or data (one-line messages for the CLI).
    """
    distributed = ddp.launched_by_torchrun()
    rank, _ = ddp.rank_and_world(distributed)
    say = print if rank == 0 else (lambda *a, **k: None)
    out = Path(args.out)
    ckpt = out / "checkpoint.pt"
    if args.steps < 1 or args.batch < 1:
        raise ValueError("--steps and --batch must be >= 1")
    if args.lr <= 0:
        raise ValueError("--lr must be > 0")
    if args.epipolar_weight < 0 or args.edge_weight < 0:
        raise ValueError("--epipolar-weight and --edge-weight must be >= 0")
    if args.init is not None and not Path(args.init).is_file():
        raise ValueError(f"--init {args.init}: no such checkpoint file")

    base: Optional[Dict[str, Any]] = None
    if args.resume and ckpt.is_file():
        _, base = load_checkpoint(ckpt)
        if args.init is not None:
            say(f"resuming {ckpt}: --init {args.init} is ignored")
    elif args.init is not None:
        _, base = load_checkpoint(args.init)
    elif args.resume:
        say(f"no {ckpt} yet: starting a new run")
    graph_config = base["graph_config"] if base else GraphConfig()
    feature_config = base["feature_config"] if base else FeatureConfig()

    train_src = data_source(args.train, seed=args.seed, train=True)
    val_src = data_source(args.val, seed=args.seed, train=False) if args.val else None
    D = _first_problem(train_src, "--train").descriptors.shape[1]
    if val_src is not None:
        check_disjoint(train_src, val_src)
        Dv = _first_problem(val_src, "--val").descriptors.shape[1]
        if Dv != D:
            raise ValueError(f"--val descriptors have D={Dv} but --train descriptors D={D}")
    in_dim = feature_dim(D, feature_config)
    if args.model_config is not None:
        d = json.loads(Path(args.model_config).read_text())
        if not isinstance(d, dict):
            raise ValueError(f"--model-config {args.model_config}: expected a JSON object of GCNConfig fields")
        d.setdefault("in_dim", in_dim)
        model_config = GCNConfig.from_dict(d)
    elif base is not None:
        model_config = base["model_config"]
    else:
        model_config = GCNConfig(in_dim=in_dim)
    if model_config.in_dim != in_dim:
        raise ValueError(f"the model takes in_dim={model_config.in_dim} features but the data gives "
                         f"{in_dim} (descriptor D={D}); use data with the model's descriptor or --model-config")
    every = max(1, min(500, args.steps // 20))
    cfg = TrainConfig(lr=args.lr, steps=args.steps, batch_size=args.batch, recon_kind=args.recon,
                      epipolar_weight=args.epipolar_weight, edge_weight=args.edge_weight, seed=args.seed,
                      val_every=every, checkpoint_every=every, log_every=max(1, min(10, every)), graph=graph_config,
                      features=feature_config)
    _, world = ddp.rank_and_world(distributed)
    say(f"train: {train_src.description}")  # type: ignore[attr-defined]
    if val_src is not None:
        say(f"val:   {val_src.description}")  # type: ignore[attr-defined]
    say(f"model: {len(model_config.widths)} layers, widths {model_config.widths[0]}..{model_config.widths[-1]}, "
        f"in_dim {model_config.in_dim}; {args.steps} steps x {args.batch} graphs"
        + (f" x {world} ranks" if world > 1 else "") + f" -> {out}")
    history = train(model_config, train_src, val_src, cfg, out, resume=args.resume, init=args.init,
                    distributed=distributed)
    if rank != 0:
        return 0
    best = history.get("best") or {}
    say(f"checkpoints: {ckpt} (step {cfg.steps}), {out / 'best.pt'}"
        + (f" (step {best['step']}, {best['source']} loss {best['loss']:.4f})" if best else ""))
    say(f"history: {out / 'history.json'}")
    plots = [out / "curves.png"] if (out / "curves.png").is_file() else []
    if val_src is not None and (out / "best.pt").is_file():
        plots += _result_plots(out, val_src, cfg.val_size)
    if plots:
        say("plots: " + ", ".join(str(p) for p in plots))
    return 0


def _result_plots(out: Path, val_src: DataSource, count: int) -> List[Path]:
    """similarity.png and histograms.png of the best model on labelled validation problems."""
    problems = [p for p in islice(val_src(0), count) if p.gt_track is not None]
    if not problems:
        return []
    loaded = load_checkpoint(out / "best.pt")
    embedded = [_embed(loaded, p) for p in problems]
    written = []
    try:
        plots.plot_similarity(problems[0], *embedded[0], out / "similarity.png")
        written.append(out / "similarity.png")
        plots.plot_similarity_histograms({"GCN": [E for E, _ in embedded]}, problems, out / "histograms.png")
        written.append(out / "histograms.png")
    except ValueError as exc:
        print(f"(no similarity plots: {exc})")
    return written


def _cmd_convert(args) -> int:
    paths = convert(args.data_root, args.out, scenes=args.scenes, sizes=tuple(args.sizes),
                             detectors=tuple(args.detectors), max_features=args.max_features)
    print(f"wrote {len(paths)} problems to {args.out}")
    return 0

def _cmd_plot(args) -> int:
    """Curves of runs; with --data, figures of their best models."""
    labels = args.labels or [r.resolve().name for r in args.runs]
    if args.labels and len(args.labels) != len(args.runs):
        raise ValueError(f"--labels: {len(args.labels)} names for {len(args.runs)} runs")
    print(plots.plot_history(args.runs, args.out, labels=labels))
    if not (args.pr or args.similarity or args.histograms):
        return 0
    if not args.data:
        raise ValueError("--pr, --similarity and --histograms need --data")
    problems = [q for q in islice(data_source(args.data, train=False)(0), args.count) if q.gt_track is not None]
    if not problems:
        raise ValueError("--data holds no problems with ground truth")
    ckpts = {lab: r / "best.pt" for lab, r in zip(labels, args.runs)}
    loaded = {lab: load_checkpoint(c) for lab, c in ckpts.items()}
    if args.pr:
        specs = {f"gcn:checkpoint={Path(p)}": lab for lab, p in ckpts.items()}
        report = evaluation.evaluate(problems, list(specs) + ["nn"], progress=False, with_reference_rows=False)
        for spec, lab in specs.items():
            report["methods"][spec]["describe"] = lab
        print(plots.plot_pr_curves(report, args.pr))
    if args.similarity:
        print(plots.plot_similarity(problems[0], *_embed(loaded[labels[0]], problems[0]), args.similarity))
    if args.histograms:
        embeddings = {lab: [_embed(m, p)[0] for p in problems] for lab, m in loaded.items()}
        print(plots.plot_similarity_histograms(embeddings, problems, args.histograms))
    return 0


def _cmd_make_bags(args) -> int:
    """Sample bags from dataset scenes (:mod:`gcn_match_ros.bags.make`)."""
    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    for scene in args.scenes:
        name = bag_make.bag_name(scene, args.detector)
        path = args.out / (name if args.storage == "mcap" else name[:-len(".mcap")])
        if path.exists():
            if not args.force:
                raise _UserError(f"{path} exists (use --force to replace it)")
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        try:
            bag_make.convert_scene_to_bag(args.data_root, scene, path, n_cameras=args.cameras,
                                          detector=args.detector, max_features=args.max_features,
                                          rate_hz=args.rate, stagger=args.stagger, storage=args.storage,
                                          progress=not args.quiet)
        except (DatasetError, ValueError) as exc:
            raise _UserError(f"{scene}: {exc}") from None
        written.append(path)
    for path in written:
        info = bag_info(path)
        size = path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.rglob("*"))
        frames = sum(n for t, n in info.counts.items() if info.topics[t] == KEYPOINTS_TYPE)
        print(f"{path}: {size / 1e6:.2f} MB, {frames} frames, {info.message_count} messages, "
              f"{len(info.topics)} topics, {(info.end_ns - info.start_ns) * 1e-9:.3f} s")
    return 0


def _window_config(cameras: Sequence[str], settings: Sequence[str]) -> WindowConfig:
    """The node's window parameters from ``name=value`` settings (the rest at their defaults)."""
    known = {p.name: p for p in window_parameters()}
    values: Dict[str, Any] = {}
    for item in settings:
        name, sep, text = item.partition("=")
        if not sep or name not in known:
            raise _UserError(f"--window '{item}': expected NAME=VALUE with NAME one of {', '.join(known)}")
        try:
            values[name] = type(known[name].default)(text)
        except ValueError:
            raise _UserError(f"--window '{item}': not a {type(known[name].default).__name__}") from None
    return WindowConfig(cameras=tuple(cameras), **values)


def _cmd_stream(args) -> int:
    """A bag solved as one stream, window by window as the matcher node solves it on replay:
    the same windows, tracks and persistent landmark ids (:func:`gcn_match_ros.stream.solve_stream`)."""
    contents = read_bag(args.bag, progress=not args.quiet)
    cameras = args.cameras or contents.cameras
    replay = contents.replay_windows(_window_config(cameras, args.window))
    if not replay.problems:
        raise _UserError(f"{args.bag}: no window of the cameras {', '.join(cameras)} forms "
                         f"(the bag's cameras: {', '.join(contents.cameras)})")
    solver = solvers.create(args.method)
    state = StreamState()
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
    ids_per_window = []
    for k, (problem, labels, stamp, (result, landmarks)) in enumerate(zip(
            replay.problems, replay.labels, replay.stamps_ns,
            solve_stream(solver, replay.problems, replay.stamps_ns, state))):
        ids_per_window.append(landmarks.ids)
        new = np.unique(landmarks.ids[(landmarks.ids >= 0) & (landmarks.ages_ns == 0)]).size
        if not args.quiet:
            print(f"window {k}: {problem.n_views} views, {problem.n_keypoints} keypoints, "
                  f"{int(result.track.max(initial=-1)) + 1} tracks, {np.unique(landmarks.ids[landmarks.ids >= 0]).size} "
                  f"landmarks ({new} new), {result.seconds * 1e3:.0f} ms", flush=True)
        if args.out:
            if labels is not None:
                problem.gt_track = window_labels(labels)
            problem.name = f"{args.bag.stem}_window_{k:04d}"
            save_problem(problem, args.out / f"window_{k:04d}.npz")
            save_result(result, args.out / f"window_{k:04d}_result.npz",
                        extra={"landmark_ids": landmarks.ids, "landmark_ages": landmarks.ages_s,
                               "stamp_ns": np.int64(stamp)})
    tracker = state.landmarks
    print(f"{args.bag.name}: {len(replay.problems)} windows by {solver.describe()}; landmarks born "
          f"{tracker.born}, live {len(tracker)}, retired {tracker.retired}"
          + (f"; written to {args.out}" if args.out else ""))
    if all(labels is not None for labels in replay.labels):
        truth = [true_points(labels, p.n_keypoints) for labels, p in zip(replay.labels, replay.problems)]
        scores = landmark_scores(ids_per_window, truth)
        print("against the bag's labels: " + ", ".join(f"{k} {v:.3f}" for k, v in scores.items()))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="gcn-match", description="Cycle-consistent multi-view keypoint matching.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    s = sub.add_parser("synth", help="write synthetic 3D-scene problems")
    s.add_argument("-o", "--out", required=True, type=Path)
    s.add_argument("--preset", default="rome16k", help="rome16k | partial | easy")
    s.add_argument("--views", type=int, default=3)
    s.add_argument("--descriptor", default="sift",
                   help="sift (SIFT-like, 128-D) | gaussian | binary (ORB-like 256-bit codes)")
    s.add_argument("--count", type=int, default=10)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--prefix", default="synth")
    s.set_defaults(func=_cmd_synth)

    m = sub.add_parser("match", help="match one problem file, write a result file")
    m.add_argument("problem", type=Path)
    m.add_argument("--method", default="gcn", help="name[:key=value,...], e.g. matchals:iters=50")
    m.add_argument("-o", "--output", required=True, type=Path)
    m.set_defaults(func=_cmd_match)

    e = sub.add_parser("eval", help="score methods on problem files and print a table")
    e.add_argument("problems", nargs="+", help="problem files or glob patterns")
    e.add_argument("--methods", default="nn,gcn",
                   help="comma-separated methods; use ';' between methods whose settings contain commas; "
                        "SPEC@REVISION: solved by the package at that git revision (before/after in one table)")
    e.add_argument("--json", type=Path, help="also write the per-problem scores as JSON")
    e.add_argument("--pr-plot", type=Path, help="write precision-recall curves (PNG)")
    e.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=_cmd_eval)

    t = sub.add_parser("train", help="train the GCN (unsupervised + optional epipolar loss)")
    t.add_argument("--train", nargs="+", required=True,
                   help="training data: problem files/globs, bag files (.mcap/.db3 or bag folders), "
                        "or synth:PRESET[:VIEWS[:DESCRIPTOR]] for generated scenes (DESCRIPTOR: sift, "
                        "gaussian, binary)")
    t.add_argument("--val", nargs="+", default=[], help="validation data, same forms as --train")
    t.add_argument("-o", "--out", required=True, type=Path, help="run directory (checkpoints, history, plots)")
    t.add_argument("--steps", type=int, default=2000)
    t.add_argument("--batch", type=int, default=4, help="graphs per step")
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--recon", choices=["l1", "l2"], default="l1")
    t.add_argument("--epipolar-weight", type=float, default=10.0,
                   help="weight of the epipolar loss on samples with poses (0 disables)")
    t.add_argument("--edge-weight", type=float, default=1.0,
                   help="weight of the edge head's pose-based loss, for models with an edge head "
                        "(the shipped ones; --init gcn_match_ros/models/default.pt fine-tunes it)")
    t.add_argument("--model-config", type=Path, help="JSON of GCNConfig fields")
    t.add_argument("--init", type=Path, help="start from this checkpoint's weights")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    t.add_argument("--seed", type=int, default=0)
    t.set_defaults(func=_cmd_train)

    c = sub.add_parser("convert", help="real images with ground truth -> problem files")
    c.add_argument("--data-root", type=Path, default=DATA_ROOT)
    c.add_argument("--scenes", nargs="+", required=True,
                   help="e.g. oxford/graf strecha/fountain-P11; homography/NAME: any sequence in the "
                        "Oxford layout (img1.png ..., H1toNp) under --data-root")
    c.add_argument("--sizes", nargs="+", type=int, default=[3, 4, 6])
    c.add_argument("--detectors", nargs="+", default=["sift"])
    c.add_argument("--max-features", type=int, default=500)
    c.add_argument("-o", "--out", required=True, type=Path)
    c.set_defaults(func=_cmd_convert)

    g = sub.add_parser("plot", help="training curves of runs, and figures of their best models")
    g.add_argument("runs", nargs="+", type=Path, help="run folders (with history.json)")
    g.add_argument("-o", "--out", required=True, type=Path, help="curves PNG")
    g.add_argument("--labels", nargs="+", help="legend names, one per run")
    g.add_argument("--data", nargs="+", help="labelled problems for --pr/--similarity/--histograms "
                                             "(same forms as train --val)")
    g.add_argument("--count", type=int, default=16, help="problems taken from --data")
    g.add_argument("--pr", type=Path, help="precision-recall PNG of the runs' best.pt (+ mutual NN)")
    g.add_argument("--similarity", type=Path, help="similarity-matrix PNG (first run, first problem)")
    g.add_argument("--histograms", type=Path, help="same/different similarity histograms PNG")
    g.set_defaults(func=_cmd_plot)

    b = sub.add_parser("make-bags", help="sample bags (a rig sliding along a scene's images) from shared/data")
    b.add_argument("--out", type=Path, required=True, help="output folder")
    b.add_argument("--data-root", type=Path, default=DATA_ROOT, help="shared/data")
    b.add_argument("--scenes", nargs="+", default=list(bag_make.DEFAULT_SCENES),
                   help=f"scene ids under --data-root (default: {' '.join(bag_make.DEFAULT_SCENES)})")
    b.add_argument("--detector", choices=("sift", "orb"), default="sift")
    b.add_argument("--max-features", type=int, default=500, help="per image, before de-duplication")
    b.add_argument("--cameras", type=int, default=3, help="cameras of the rig (views per window)")
    b.add_argument("--rate", type=float, default=2.0, help="rig captures per second")
    b.add_argument("--stagger", type=float, default=0.002, help="camera j is stamped j * STAGGER s later")
    b.add_argument("--storage", choices=STORAGES, default="mcap",
                   help="mcap: single .mcap files; sqlite3: rosbag2 directories")
    b.add_argument("--force", action="store_true", help="replace existing bags")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    b.set_defaults(func=_cmd_make_bags)

    r = sub.add_parser("stream", help="solve a bag as one stream, as the matcher node does on replay "
                                      "(tracks and persistent landmark ids)")
    r.add_argument("bag", type=Path, help="a bag (.mcap / .db3 or a bag folder) with <camera>/keypoints topics")
    r.add_argument("--method", default="gcn", help="the node's solver parameter, e.g. gcn or nn-ransac")
    r.add_argument("--cameras", nargs="+", help="camera ids in window order (default: the bag's)")
    r.add_argument("--window", nargs="+", default=[], metavar="NAME=VALUE",
                   help="the node's window parameters, e.g. max_keypoints=500 sync_tolerance=0.05")
    r.add_argument("-o", "--out", type=Path, help="write each window's problem (window_NNNN.npz, with the "
                                                   "bag's labels as gt_track) and result (window_NNNN_result.npz, "
                                                   "plus landmark_ids, landmark_ages [s], stamp_ns)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress")
    r.set_defaults(func=_cmd_stream)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line; returns the exit status."""
    distributed = ddp.launched_by_torchrun()
    if distributed:
        ddp.init_process_group()
    try:
        args = build_parser().parse_args(argv)
        single_blas_thread()
        return int(args.func(args) or 0)
    except (_UserError, ValueError, OSError, KeyError) as exc:  # FormatError, CheckpointError are ValueErrors
        if os.environ.get("GCN_MATCH_DEBUG"):
            raise
        where = f" (rank {ddp.rank_and_world(True)[0]})" if distributed else ""
        print(f"gcn-match: error{where}: {exc}", file=sys.stderr)
    except KeyboardInterrupt:
        print("gcn-match: interrupted", file=sys.stderr)
        return 130
    finally:
        if distributed:
            ddp.destroy_process_group()
    return 2


if __name__ == "__main__":
    sys.exit(main())
