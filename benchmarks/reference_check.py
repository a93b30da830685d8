#!/usr/bin/env python
"""Check the solver ports against the authors' originals on the 16 dev Oxford problems.

The reference (shared/reference/oxford-dev/reference_scores.json) holds the scores of the
MATLAB originals run under Octave on the same problems with the same input graph (binary
mutual nearest neighbours, with or without Lowe's ratio 0.8, identity on the diagonal).
For every (our setting, reference row) pair this prints our mean P / R / F1 / AP and median
seconds beside the reference's, and ΔF1 = ours − reference; a faithful port lands within a
few hundredths of F1 (random initialisation aside).

Usage:
    python benchmarks/reference_check.py                       # every method with a reference row
    python benchmarks/reference_check.py --methods clear,matcheig
    python benchmarks/reference_check.py --methods pgdds       # no reference row: ours only
    python benchmarks/reference_check.py --methods matchals --problems '_(123|234)$' --per-problem

Seconds are ours (Python, this machine, graph build + solve + rounding) against Octave's:
compare them loosely. The slow dense methods (matchals, pgdds) dominate the runtime;
``--problems`` restricts the set of problems (a regular expression on the name).

``--blas-threads N`` caps the BLAS / OpenMP thread pools (set before numpy loads). On a
machine whose cores are shared with other jobs, multi-threaded OpenBLAS can be 10-100x
slower on MatchALS / PGDDS than one thread (its workers spin while the cores are busy).
"""
from __future__ import annotations

import os
import sys


def _cap_threads(argv) -> None:
    """Apply --blas-threads before numpy is imported (the pools are sized at load time)."""
    for i, arg in enumerate(argv):
        value = arg.split("=", 1)[1] if arg.startswith("--blas-threads=") else \
            (argv[i + 1] if arg == "--blas-threads" and i + 1 < len(argv) else None)
        if value:
            for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
                os.environ[var] = value


_cap_threads(sys.argv[1:])

import argparse  # noqa: E402
import json  # noqa: E402
import re  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from gcn_match_ros import solvers  # noqa: E402
from gcn_match_ros.metrics import mean_scores, score_result  # noqa: E402
from gcn_match_ros.problem import load_problem  # noqa: E402
from gcn_match_ros.rounding import is_cycle_consistent  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO.parent / "shared" / "reference" / "oxford-dev"

#: method -> [(our solver spec, reference row or None)]
CHECKS = {
    "nn": [("nn:graph=mutual", "nn-floor:mutual"),
           ("nn:graph=ratio0.8", "nn-floor:mutual,ratio=0.8")],
    "spectral": [("spectral:graph=mutual", "spectral:nn,d=est,round=0.5"),
                 ("spectral:graph=ratio0.8", None)],
    "matcheig": [("matcheig:graph=mutual", "matcheig:nn,d=est,t=0.25"),
                 ("matcheig:graph=mutual,rounding=repair,soft=binary", "matcheig:nn,d=est,t=0.25"),
                 ("matcheig:graph=ratio0.8", "matcheig:nn-ratio0.8,d=est,t=0.25"),
                 ("matcheig:graph=ratio0.8,rounding=repair,soft=binary", "matcheig:nn-ratio0.8,d=est,t=0.25")],
    "clear": [("clear:graph=mutual", "clear:nn,d=est-by-clear"),
              ("clear:graph=ratio0.8", "clear:nn-ratio0.8,d=est-by-clear")],
    "matchals": [("matchals:graph=mutual", "matchals:nn,r=2maxv,it=50,round"),
                 ("matchals:graph=mutual,rounding=repair", "matchals:nn,r=2maxv,it=50,raw>0.5"),
                 ("matchals:graph=mutual,rounding=greedy", "matchals:nn,r=2maxv,it=50,raw>0.5")],
    "pgdds": [("pgdds:graph=mutual", None),
              ("pgdds:graph=ratio0.8", None)],  # no reference row: run only with --methods
    "quickmatch": [("quickmatch:graph=mutual", "quickmatch:nn"),
                   ("quickmatch:graph=ratio0.8", "quickmatch:nn-ratio0.8")],
}
DEFAULT_METHODS = [m for m in CHECKS if m != "pgdds"]
KEYS = ("P", "R", "F1", "AP")


def run_check(spec: str, problems, per_problem: bool, ref_rows):
    solver = solvers.create(spec)
    rows = []
    for prob in problems:
        res = solver.solve(prob)
        if not is_cycle_consistent(res.track, prob.view_index):
            raise AssertionError(f"{spec}: tracks not cycle-consistent on {prob.name}")
        sc = score_result(prob, res)
        rows.append(sc)
        if per_problem:
            ref = (ref_rows or {}).get(prob.name)
            line = f"    {prob.name:28s} " + " ".join(f"{k}={sc[k]:.3f}" for k in KEYS) + f" s={sc['seconds']:.2f}"
            if ref:
                line += "  | ref " + " ".join(f"{k}={ref[k]:.3f}" for k in KEYS) + f"  dF1={sc['F1'] - ref['F1']:+.3f}"
            print(line, flush=True)
    return mean_scores(rows)


def reference_mean(ref_rows, names):
    vals = [ref_rows[n] for n in names]
    out = {k: float(np.mean([v[k] for v in vals])) for k in KEYS}
    out["seconds"] = float(np.median([v["seconds"] for v in vals]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                    help=f"comma-separated subset of {','.join(CHECKS)} (default: all but pgdds)")
    ap.add_argument("--problems", default="", help="regular expression selecting problems by name, e.g. '_(123|234)$' (default: all 16)")
    ap.add_argument("--per-problem", action="store_true", help="print every problem's scores")
    ap.add_argument("--reference", default=str(REFERENCE), help="reference directory (problems/ + reference_scores.json)")
    ap.add_argument("--blas-threads", type=int, default=None,
                    help="cap BLAS/OpenMP threads (applied before numpy loads; see above)")
    args = ap.parse_args(argv)

    ref_dir = Path(args.reference)
    ref = json.loads((ref_dir / "reference_scores.json").read_text())
    files = sorted((ref_dir / "problems").glob("*.npz"))
    if args.problems:
        pattern = re.compile(args.problems)
        files = [f for f in files if pattern.search(f.stem)]
    if not files:
        print("no problems selected", file=sys.stderr)
        return 2
    problems = [load_problem(f) for f in files]
    names = [p.name for p in problems]
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in CHECKS]
    if unknown:
        print(f"unknown methods {unknown}; choose from {list(CHECKS)}", file=sys.stderr)
        return 2

    header = (f"{'method (ours)':52s} {'F1':>6s} {'AP':>6s} {'s':>6s} | {'reference row':36s} "
              f"{'F1':>6s} {'AP':>6s} {'s':>6s} | {'dF1':>6s}")
    print(f"{len(problems)} problems: {', '.join(names)}")
    table = []
    for m in methods:
        for spec, ref_key in CHECKS[m]:
            ref_rows = ref["per_problem"].get(ref_key) if ref_key else None
            if args.per_problem:
                print(f"  {spec}")
            ours = run_check(spec, problems, args.per_problem, ref_rows)
            r = reference_mean(ref_rows, names) if ref_rows else None
            line = f"{spec:52s} {ours['F1']:6.3f} {ours['AP']:6.3f} {ours['seconds']:6.2f} | "
            if r:
                line += (f"{ref_key:36s} {r['F1']:6.3f} {r['AP']:6.3f} {r['seconds']:6.2f} | "
                         f"{ours['F1'] - r['F1']:+6.3f}")
            else:
                line += f"{'(no reference row)':36s} {'':6s} {'':6s} {'':6s} |"
            table.append(line)
            print(line, flush=True)
    print()
    print(header)
    print("-" * len(header))
    for line in table:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
