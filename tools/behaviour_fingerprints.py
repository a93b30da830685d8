#!/usr/bin/env python
"""Fingerprints of the package's outputs, to show that a change of code changes no result.

    ./run.sh python tools/behaviour_fingerprints.py before.json                 # on the old commit
    ./run.sh python tools/behaviour_fingerprints.py after.json --against before.json

Hashes (sha256 of the exact bytes) of: the labelled problems of every scene of
``../shared/data`` (SIFT and ORB, windows of 3, 4 and 6 views; photometric labels of three pose
windows), every solver's result, candidate edges and graph on 28 of those windows, generated
scenes and their solutions, the permutation-noise protocol, the windows of the sample bags,
a bag made from a scene and read back, windows trimmed to ``max_keypoints``, and a short
training run from the shipped model. ``--sections`` runs a subset. About 7 minutes on 2 cores
(``solvers`` is most of it). Exit status 1 when ``--against`` finds a difference.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from gcn_match_ros import solvers
from gcn_match_ros.bags.contents import read_bag
from gcn_match_ros.bags.make import convert_scene_to_bag
from gcn_match_ros.bags.source import BagSource
from gcn_match_ros.data import synthetic
from gcn_match_ros.data.convert import convert, make_problem
from gcn_match_ros.data.permutation_noise import PAPER_SYNTHETIC_ROWS, permutation_noise_problem
from gcn_match_ros.data.scenes import DATA_ROOT, load_scene
from gcn_match_ros.edges.candidates import EdgeConfig, candidate_edges
from gcn_match_ros.graph import GraphConfig, build_graph
from gcn_match_ros.learn.checkpoint import load_checkpoint
from gcn_match_ros.learn.config import TrainConfig
from gcn_match_ros.learn.sources import data_source
from gcn_match_ros.learn.train import train
from gcn_match_ros.problem import load_problem
from gcn_match_ros.solvers.gcn import DEFAULT_CHECKPOINT
from gcn_match_ros.windowing import WindowConfig, window_problem

REPO = Path(__file__).resolve().parents[1]
SCENES = ["oxford/graf", "oxford/boat", "oxford/bikes", "oxford/wall", "strecha/fountain-P11", "strecha/entry-P10",
          "strecha/castle-P19", "middlebury_temple"]
METHODS = ["gcn", "nn", "nn-ransac", "nn-ransac:guided=true", "spectral", "matcheig", "clear", "quickmatch",
           "gcn:descriptor_fallback=false", "nn:graph=mutual"]
SLOW = ["matchals", "pgdds"]  # 3-view windows under 1300 keypoints only
SECTIONS = ("problems", "solvers", "synthetic", "bags", "train")


def digest(*arrays) -> str:
    m = hashlib.sha256()
    for a in arrays:
        if a is None:
            m.update(b"None")
        elif isinstance(a, str):
            m.update(a.encode())
        else:
            a = np.ascontiguousarray(np.asarray(a))
            m.update(str(a.dtype).encode() + str(a.shape).encode())
            m.update(a.tobytes())
    return m.hexdigest()[:16]


def problem_digest(p) -> str:
    return digest(p.view_offsets, p.keypoints, p.descriptors, p.scales, p.orientations, p.K, p.R, p.t,
                  p.image_size, p.gt_track)


def result_digest(r) -> str:
    return digest(r.track, r.pair_rows, r.pair_cols, r.pair_scores)


def fingerprints(sections, tmp: Path, log) -> dict:
    out = {}
    problems = {}
    if {"problems", "solvers"} & set(sections):
        for det in ("sift", "orb"):
            for path in convert(DATA_ROOT, tmp / det, SCENES, sizes=(3, 4, 6), detectors=(det,), progress=False):
                p = load_problem(path)
                problems[p.name] = p
                out[f"problem/{p.name}"] = problem_digest(p)
        for scene, views in (("strecha/castle-P19", (0, 1, 2)), ("strecha/entry-P10", (2, 3, 4, 5)),
                             ("middlebury_temple", (0, 1, 2))):
            p = make_problem(load_scene(DATA_ROOT, scene), views, "sift", 500, None, "photometric")
            out[f"photometric/{p.name}"] = problem_digest(p)
        log("problems")
    made = {m: solvers.create(m) for m in METHODS + SLOW}
    if "solvers" in sections:
        names = sorted(problems)
        subset = ([n for n in names if n.endswith(("_123", "_2345", "_123456"))]
                  + [n for n in names if "strecha" in n or "temple" in n][::7])
        for n in subset:
            p = problems[n]
            for m in METHODS + (SLOW if p.n_views == 3 and p.n_keypoints < 1300 else []):
                out[f"solve/{m}/{n}"] = result_digest(made[m].solve(p))
            for label, cfg in (("default", EdgeConfig()), ("nnr", EdgeConfig(k=1, guided=True, normalization="l2"))):
                es = candidate_edges(p, cfg)
                out[f"edges/{label}/{n}"] = digest(es.rows, es.cols, es.features, es.res_px, es.confident)
            g = build_graph(p, GraphConfig())
            out[f"graph/{n}"] = digest(g.rows, g.cols, g.weights, g.cosine, g.ratio, g.rank)
        log("solvers")
    if "synthetic" in sections:
        for preset in ("rome16k", "partial", "easy"):
            for kind in ("sift", "gaussian", "binary"):
                for views in (3, 4):
                    cfg = synthetic.preset(preset, views, kind)
                    for seed in range(3):
                        p = synthetic.random_scene_problem(cfg, np.random.default_rng([seed, 7]))
                        out[f"synth/{preset}/{kind}/{views}/{seed}"] = problem_digest(p)
                        if seed == 0:
                            for m in ("gcn", "nn", "nn-ransac:guided=true", "matcheig"):
                                out[f"synth-solve/{m}/{preset}/{kind}/{views}"] = result_digest(made[m].solve(p))
        for row, kw in PAPER_SYNTHETIC_ROWS.items():
            p, g = permutation_noise_problem(n_views=4, rng=np.random.default_rng(3), **kw)
            out[f"perm/{row}"] = problem_digest(p) + digest(g.rows, g.cols, g.weights)
            for m in ("spectral", "matcheig", "clear", "nn"):
                out[f"perm-solve/{m}/{row}"] = result_digest(made[m].solve(p, graph=g))
        log("synthetic")
    if "bags" in sections:
        for bag in ("oxford_graf_sift", "strecha_fountain_sift", "oxford_boat_orb"):
            src = BagSource(REPO / "bags" / f"{bag}.mcap", shuffle=False, cycle=False, progress=False)
            for i, p in enumerate(src.problems):
                out[f"bag/{bag}/{i}"] = problem_digest(p)
            for i, (_, frames) in enumerate(src.window_frames):
                out[f"bagframes/{bag}/{i}"] = digest(str(frames))
        for scene, det in (("oxford/graf", "sift"), ("strecha/fountain-P11", "orb")):
            path = tmp / f"{det}.mcap"
            convert_scene_to_bag(DATA_ROOT, scene, path, n_cameras=3, detector=det, max_features=300, progress=False)
            c = read_bag(path, progress=False)
            for cam in c.cameras:
                for i, f in enumerate(c.frames[cam]):
                    out[f"madebag/{det}/{cam}/{i}"] = digest(
                        f.keypoints, f.descriptors, f.scales, f.orientations, f.K, f.R, f.t, c.labels[cam][i],
                        str(f.stamp_ns), str(f.image_size), f.frame_id)
        c = read_bag(REPO / "bags" / "strecha_fountain_sift.mcap", progress=False)
        for i, (frames, labels) in enumerate(c.windows(WindowConfig(cameras=tuple(c.cameras), max_keypoints=200))):
            out[f"trim/{i}"] = problem_digest(window_problem(frames)) + digest(labels)
        log("bags")
    if "train" in sections:
        _, meta = load_checkpoint(DEFAULT_CHECKPOINT)
        tr = data_source([str(REPO / "bags" / "strecha_fountain_sift.mcap"), "synth:partial:3"], seed=0, train=True)
        va = data_source([str(REPO / "bags" / "oxford_graf_sift.mcap")], seed=0, train=False)
        cfg = TrainConfig(steps=6, batch_size=2, val_every=3, checkpoint_every=3, log_every=2, edge_weight=1.0,
                          progress=False, plot=False, graph=meta["graph_config"], features=meta["feature_config"])
        hist = train(meta["model_config"], tr, va, cfg, tmp / "run", init=DEFAULT_CHECKPOINT)
        model, _ = load_checkpoint(tmp / "run" / "checkpoint.pt")
        out["train/state"] = digest(*[v.numpy() for _, v in sorted(model.state_dict().items())])
        out["train/history"] = digest(json.dumps([{k: v for k, v in e.items() if k != "seconds"}
                                                  for e in hist["train"]] + hist["val"], sort_keys=True))
        log("train")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="JSON file of fingerprints to write")
    ap.add_argument("--against", type=Path, help="fingerprints of another commit to compare with")
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        prints = fingerprints(args.sections, Path(tmp), lambda what: print(f"{what}: {time.time() - t0:.0f} s",
                                                                           flush=True))
    args.out.write_text(json.dumps(prints, indent=0, sort_keys=True))
    print(f"{len(prints)} fingerprints -> {args.out}")
    if args.against is None:
        return 0
    base = json.loads(args.against.read_text())
    common = [k for k in prints if k in base]
    differ = [k for k in common if prints[k] != base[k]]
    print(f"against {args.against}: {len(common)} compared, {len(differ)} different, "
          f"{len(prints) - len(common)} only here, {len(base) - len(common)} only there")
    for k in differ[:50]:
        print("  DIFFERENT", k)
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
