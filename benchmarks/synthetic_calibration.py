"""Calibration of the generated scenes (gcn_match_ros.data.synthetic): how hard each preset is.

For every preset: precision, recall and F1 of plain mutual nearest neighbours on the
descriptors (synthetic.mutual_nn_prf; counts pooled over --count problems, seeds
--seeds-from ..), the descriptor noise used, and the generation time per problem. For the
rows of the paper's permutation-noise protocol (permutation_noise.PAPER_SYNTHETIC_ROWS): the
mean wrong-match rate of the given graph (permutation_noise.graph_outlier_rate). The
table in the data.synthetic and data.permutation_noise docstrings comes from this script.

    .venv/bin/python benchmarks/synthetic_calibration.py               # 200 problems a row
    .venv/bin/python benchmarks/synthetic_calibration.py --count 20 --out /tmp/calibration.md
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from gcn_match_ros.data.permutation_noise import PAPER_SYNTHETIC_ROWS, graph_outlier_rate, permutation_noise_problem
from gcn_match_ros.data.synthetic import easy, mutual_nn_prf, partial, random_scene_problem, rome16k
from gcn_match_ros.experiments import results_header, write_results

REPO = Path(__file__).resolve().parents[1]


def presets():
    """(label, SceneConfig) of every calibrated preset."""
    return [("rome16k(3)", rome16k(3)), ("rome16k(4)", rome16k(4)), ("partial(3)", partial(3)),
            ("partial(4)", partial(4)), ("easy(3)", easy(3)),
            ("rome16k(3) forward", rome16k(3, layout="forward")),
            ("rome16k(3) gaussian", rome16k(3, descriptor_kind="gaussian")),
            ("rome16k(3) binary", rome16k(3, descriptor_kind="binary")),
            ("partial(3) binary", partial(3, descriptor_kind="binary"))]


def noise_of(cfg) -> str:
    """The descriptor noise of a config as the docstring table writes it."""
    return f"flip {cfg.sigma:.2f}" if cfg.descriptor_kind == "binary" else f"σ {cfg.sigma:.2f}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=200, help="problems per row")
    ap.add_argument("--seeds-from", type=int, default=0, help="first seed (problem i uses seed SEEDS_FROM + i)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "synthetic_calibration.md"))
    args = ap.parse_args(argv)
    n, first = args.count, args.seeds_from
    lines = results_header("Calibration of the generated scenes", __file__, argv) + [
        f"Plain mutual nearest neighbours on the descriptors (data.synthetic.mutual_nn_prf), counts pooled over "
        f"{n} problems per preset (seeds {first}..{first + n - 1}); ms/problem: generation time.\n",
        "| preset | P | R | F1 | descriptor noise | ms/problem |", "|---|---|---|---|---|---|"]
    print(f"{'preset':24s} {'P':>6s} {'R':>6s} {'F1':>6s}  ms/problem")
    t_start = time.time()
    for label, cfg in presets():
        tp = pred = true = 0
        t0 = time.perf_counter()
        probs = [random_scene_problem(cfg, first + s) for s in range(n)]
        dt = (time.perf_counter() - t0) / n
        for prob in probs:
            _, _, _, a, b, c = mutual_nn_prf(prob)
            tp, pred, true = tp + a, pred + b, true + c
        p, r = tp / pred, tp / true
        f1 = 2 * p * r / (p + r)
        print(f"{label:24s} {p:6.3f} {r:6.3f} {f1:6.3f}  {1000 * dt:.1f}", flush=True)
        lines.append(f"| {label} | {p:.3f} | {r:.3f} | {f1:.3f} | {noise_of(cfg)} | {1000 * dt:.1f} |")
    lines += ["", f"Permutation-noise protocol (data.permutation_noise, 3 views, p = 25): mean wrong-match rate of "
                  f"the given graph over {n} problems (seeds 0..{n - 1}).\n",
              "| row | wrong-match rate |", "|---|---|"]
    for row, kw in PAPER_SYNTHETIC_ROWS.items():
        rates = [graph_outlier_rate(g, pr.gt_track)
                 for pr, g in (permutation_noise_problem(3, rng=s, **kw) for s in range(n))]
        print(f"permutation {row:16s} wrong-match rate {np.mean(rates):.3f}", flush=True)
        lines.append(f"| {row} | {np.mean(rates):.3f} |")
    lines.append(f"\nWall time {time.time() - t_start:.0f} s.")
    write_results(args.out, "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
