"""``gcn-match``: synthesise problems, match them with any method, score and train.

    gcn-match synth -o DIR [--preset rome16k|partial|easy] [--views 3] [--descriptor sift|gaussian|binary]
                    [--count 10] [--seed 0]
    gcn-match match PROBLEM.npz --method gcn -o RESULT.npz
    gcn-match eval PROBLEM.npz... --methods nn,gcn,matchals [--json OUT] [--pr-plot PNG]
    gcn-match train --train DATA... --val DATA... -o RUN_DIR [--steps N] [--resume]
    gcn-match convert --scenes oxford/graf strecha/fountain-P11 -o DIR   (real images -> problems)

Every failure caused by arguments or input files prints one line (``gcn-match: error: ...``)
and exits with status 2; no traceback.
"""
from __future__ import annotations

import argparse
import glob
import json
import os
import sys
from pathlib import Path
from typing import List, Optional, Sequence

__all__ = ["main"]


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


# -- subcommands ---------------------------------------------------------------
def _cmd_synth(args) -> int:
    from . import synthetic

    config = synthetic.preset(args.preset, args.views, args.descriptor)
    paths = synthetic.write_problems(args.out, lambda rng: synthetic.random_scene_problem(config, rng),
                                     count=args.count, seed=args.seed, prefix=args.prefix)
    print(f"wrote {len(paths)} problems to {args.out}")
    return 0


def _cmd_match(args) -> int:
    from .problem import load_problem, save_result
    from .solvers import get_solver

    problem = load_problem(args.problem)
    result = get_solver(args.method).solve(problem)
    save_result(result, args.output)
    n_tracks = int(result.track.max(initial=-1)) + 1
    print(f"{problem.name}: {result.method}: {n_tracks} tracks, {result.pair_rows.size} scored pairs, "
          f"{result.seconds * 1e3:.1f} ms -> {args.output}")
    return 0


def _cmd_eval(args) -> int:
    from .evaluation import evaluate, format_table, plot_pr_curves

    problems = _expand(args.problems)
    methods = [m for m in args.methods.split(";" if ";" in args.methods else ",") if m]
    report = evaluate(problems, methods, progress=not args.quiet)
    print(format_table(report))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    if args.pr_plot:
        plot_pr_curves(report, args.pr_plot)
    return 0


def _cmd_train(args) -> int:
    from .train import run_from_args

    return run_from_args(args)


def _cmd_convert(args) -> int:
    from . import datasets

    paths = datasets.convert(args.data_root, args.out, scenes=args.scenes, sizes=tuple(args.sizes),
                             detectors=tuple(args.detectors), max_features=args.max_features)
    print(f"wrote {len(paths)} problems to {args.out}")
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
                   help="comma-separated methods; use ';' between methods whose settings contain commas")
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
    c.add_argument("--data-root", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    c.add_argument("--scenes", nargs="+", required=True,
                   help="e.g. oxford/graf strecha/fountain-P11; homography/NAME: any sequence in the "
                        "Oxford layout (img1.png ..., H1toNp) under --data-root")
    c.add_argument("--sizes", nargs="+", type=int, default=[3, 4, 6])
    c.add_argument("--detectors", nargs="+", default=["sift"])
    c.add_argument("--max-features", type=int, default=500)
    c.add_argument("-o", "--out", required=True, type=Path)
    c.set_defaults(func=_cmd_convert)
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the command line; GCN_MATCH_DEBUG=1 shows tracebacks instead of one-line errors."""
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except (_UserError, ValueError, OSError, KeyError) as exc:  # FormatError, CheckpointError are ValueErrors
        if os.environ.get("GCN_MATCH_DEBUG"):
            raise
        print(f"gcn-match: error: {exc}", file=sys.stderr)
    except KeyboardInterrupt:
        print("gcn-match: interrupted", file=sys.stderr)
        return 130
    return 2


if __name__ == "__main__":
    sys.exit(main())
