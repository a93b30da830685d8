"""With and without the geometric (pose) losses: the shipped SIFT recipe against ablations.

Every run is benchmarks/train_default.py with the shipped recipe (same data, split by scene,
synthetic scenes mixed in, seed, steps); only the loss terms differ:

- ``full``: reconstruction + epipolar (weight 10) + edge-head loss — the recipe of default.pt;
- ``no-epipolar``: reconstruction + edge-head loss (no epipolar term on the embeddings);
- ``paper``: reconstruction + epipolar, no edge head (the paper's training; EEᵀ is the score);
- ``recon-only``: reconstruction alone, no edge head — no poses used at all.

Each final checkpoint is scored on the 8 validation windows and on the 25 held-out SIFT
windows (all Oxford + castle-P19) and 12 generated scenes (rome16k / partial presets, seeds
no training stream uses), with the rounding threshold chosen on validation among 0.1, 0.2,
0.3, 0.5 and 0.7. Writes the table and two figures next to ``--out``: training/validation
curves of all runs overlaid (the epipolar loss is logged for every run, also where it is
not trained on) and precision-recall curves on the held-out windows.

    .venv/bin/python benchmarks/geometric_loss_ablation.py            # ~15 min on 2 cores
    .venv/bin/python benchmarks/geometric_loss_ablation.py --steps 200 --runs /tmp/abl_quick
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros.data import synthetic
from gcn_match_ros.evaluation import evaluate
from gcn_match_ros.experiments import results_header, write_results, role, split, windows
from gcn_match_ros.plots import plot_history, plot_pr_curves
from gcn_match_ros.problem import load_problem

REPO = Path(__file__).resolve().parents[1]

RUNS = {
    "full": ["--epipolar-weight", "10", "--edge-weight", "1"],
    "no-epipolar": ["--epipolar-weight", "0", "--edge-weight", "1"],
    "paper": ["--epipolar-weight", "10", "--edge-weight", "0"],
    "recon-only": ["--epipolar-weight", "0", "--edge-weight", "0"],
}
RECIPE = ["--synthetic", "rome16k,partial"]  # as default.pt (models/README.md)
THRESHOLDS = (0.1, 0.2, 0.3, 0.5, 0.7)


def finished(run: Path, steps: int) -> bool:
    """A run folder whose history reaches ``steps`` (re-running the script reuses it)."""
    try:
        hist = json.loads((run / "history.json").read_text())
        return (run / "checkpoint.pt").is_file() and max(e["step"] for e in hist["train"]) >= steps
    except (OSError, ValueError, KeyError):
        return False


def train_all(runs_dir: Path, data: Path, steps: int, jobs: int) -> None:
    """Train the missing runs, ``jobs`` at a time (one torch thread each)."""
    todo = [name for name in RUNS if not finished(runs_dir / name, steps)]
    running = []
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    while todo or running:
        while todo and len(running) < jobs:
            name = todo.pop(0)
            cmd = [sys.executable, str(REPO / "benchmarks" / "train_default.py"), "--data", str(data),
                   "--steps", str(steps), "--out", str(runs_dir / name)] + RECIPE + RUNS[name]
            log = open(runs_dir / f"{name}.log", "w")
            print("training", name, flush=True)
            running.append((name, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log))
        time.sleep(2)
        for item in list(running):
            name, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                if proc.returncode != 0:
                    raise SystemExit(f"run {name} failed (rc {proc.returncode}); see {runs_dir / name}.log")
                print("finished", name, flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--jobs", type=int, default=2, help="runs trained at once")
    ap.add_argument("--runs", default="/tmp/real_gcn/ablation_synth", help="run folders (reused when complete)")
    ap.add_argument("--data", default="/tmp/real_gcn/sift",
                    help="SIFT problems of all scenes (as made by benchmarks/real_eval.py)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "geometric_loss_ablation.md"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    runs_dir = Path(args.runs)
    runs_dir.mkdir(parents=True, exist_ok=True)
    data = Path(args.data)
    if not list(data.glob("oxford_*.npz")):
        raise SystemExit(f"{data}: no Oxford problems; run benchmarks/real_eval.py first (it makes them)")
    train_all(runs_dir, data, args.steps, args.jobs)

    names = windows(sorted(f.stem for f in data.glob("*.npz") if not f.stem.startswith("middlebury")), False)
    test = [load_problem(data / f"{n}.npz") for n in names if role(n) == "test"]
    val = [load_problem(f) for f in split(sorted(data.glob("*.npz")))[1]]  # the trainer's 8 windows
    # generated scenes never trained on (training streams use seeds [0, k])
    synth = [synthetic.random_scene_problem(preset(3 + i % 2), np.random.default_rng([7, i]), name=f"{preset.__name__}{i}")
             for i in range(6) for preset in (synthetic.rome16k, synthetic.partial)]
    rows, test_methods, train_seconds = [], {}, {}
    for name in RUNS:
        ckpt = runs_dir / name / "checkpoint.pt"
        specs = [f"gcn:checkpoint={ckpt},threshold={t}" for t in THRESHOLDS]
        rv = evaluate(val, specs, progress=False, with_reference_rows=False)["methods"]
        best = max(specs, key=lambda s: rv[s]["mean"]["F1"])
        rt = evaluate(test, [best], progress=False, with_reference_rows=False)["methods"][best]
        rs = evaluate(synth, [best], progress=False, with_reference_rows=False)["methods"][best]
        hist = json.loads((runs_dir / name / "history.json").read_text())
        last_val = hist["val"][-1]
        train_seconds[name] = hist["train"][-1].get("seconds", float("nan"))
        rows.append((name, " ".join(RUNS[name]), best.rsplit("=", 1)[1], rv[best]["mean"]["F1"],
                     rt["mean"]["F1"], rt["mean"]["AP"], rs["mean"]["F1"], last_val.get("recon", float("nan")),
                     last_val.get("epipolar", float("nan"))))
        test_methods[best] = dict(rt, describe=name)  # its held-out scores and PR curve, labelled by run
        print(rows[-1], flush=True)
    report = evaluate(test, ["nn"], progress=False, with_reference_rows=False)
    report["methods"] = {**test_methods, **report["methods"]}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    curves = plot_history([runs_dir / n for n in RUNS], out.with_name("geometric_loss_curves.png"),
                          labels=list(RUNS), title="SIFT training: with and without the geometric losses")
    pr = out.with_name("geometric_loss_pr.png")
    plot_pr_curves(report, pr)
    lines = results_header("With and without the geometric losses (SIFT)", __file__, argv,
                           torch_threads="1 per run") + [
        f"Training time per run (its history; runs trained {args.jobs} at a time): "
        + ", ".join(f"{n} {t:.0f} s" for n, t in train_seconds.items()) + "  ",
        f"Each run: benchmarks/train_default.py --steps {args.steps} {' '.join(RECIPE)} (seed 0, same data "
        "and split) with the flags below. Threshold: the best of 0.1/0.2/0.3/0.5/0.7 on validation F1. Validation: 8 fountain/entry "
        "windows (images >= 6); held-out: 25 SIFT windows (all Oxford + castle-P19); synthetic: 12 generated "
        "scenes (rome16k / partial, 3-4 views, unseen seeds). Losses: the "
        "validation losses at the last step (epipolar logged for every run, trained on only where "
        "its weight is > 0).\n",
        "| run | flags | threshold | val F1 | held-out F1 | held-out AP | synthetic F1 | val recon | val epipolar |",
        "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r[0]} | `{r[1]}` | {r[2]} | {r[3]:.3f} | {r[4]:.3f} | {r[5]:.3f} | {r[6]:.3f} | {r[7]:.4f} "
                     f"| {r[8]:.4f} |")
    nn = report["methods"]["nn"]["mean"]
    nn_synth = evaluate(synth, ["nn:graph=mutual"], progress=False, with_reference_rows=False)["methods"]
    lines.append(f"| nn (reference; synthetic: nn:graph=mutual) | | | | {nn['F1']:.3f} | {nn['AP']:.3f} "
                 f"| {nn_synth['nn:graph=mutual']['mean']['F1']:.3f} | | |")
    lines.append(f"\nFigures: `{curves.name}` (curves), `{pr.name}` (held-out precision-recall).")
    write_results(out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
