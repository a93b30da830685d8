"""Part B of the ORB confirmation (benchmarks/results/orb_confirmation_protocol.md): every method
on homography sequences made from photographs this project has never used.

The photographs are those of the scikit-image 0.25.2 wheel (``skimage/data/``), downloaded once
into --cache with pip (no install; the file's sha256 is checked) and read from the zip. Each
becomes a 6-view sequence (homography_sequence.py, protocol defaults, seed [20261123, scene
index]) under <data>/homography/<name>; problems (ORB and SIFT 500, consecutive windows of 3, 4
and 6 views, labels as Oxford's) go to <data>/<detector>.

    .venv/bin/python benchmarks/orb_confirmation.py     # ~15 min on 2 cores

Part A (the held-out real scenes at 1000 ORB keypoints) is a real_eval.py run; its command is in
benchmarks/results/orb_confirmation_part_a.md.
"""
from __future__ import annotations

import argparse
import functools
import hashlib
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from gcn_match_ros.data.convert import convert
from gcn_match_ros.data.homography_sequence import make_sequence
from gcn_match_ros.evaluation import evaluate, format_table
from gcn_match_ros.experiments import lead_lines, results_header, write_results
from gcn_match_ros.metrics import count_pairs
from gcn_match_ros.problem import load_problem

REPO = Path(__file__).resolve().parents[1]

WHEEL = "scikit_image-0.25.2-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl"
WHEEL_SHA256 = "24cc986e1f4187a12aa319f777b36008764e856e5013666a4a83f8df083c2641"
# the protocol's list, in its order (the order gives each scene its seed)
PHOTOS = ["astronaut.png", "brick.png", "camera.png", "cell.png", "chelsea.png", "clock_motion.png", "coffee.png",
          "coins.png", "grass.png", "gravel.png", "hubble_deep_field.jpg", "ihc.png", "moon.png",
          "motorcycle_left.png", "retina.jpg", "rocket.jpg"]
SEED = 20261123
METHODS = ["clear", "gcn", "gcn:threshold=0.1", "matcheig", "nn", "nn-ransac", "nn-ransac:guided=true",
           "quickmatch", "spectral"]


def fetch_wheel(cache: Path) -> Path:
    """The scikit-image wheel in ``cache`` (downloaded with pip if missing), sha256 checked."""
    path = cache / WHEEL
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "scikit-image==0.25.2", "--no-deps",
                        "--only-binary=:all:", "--platform", "manylinux2014_x86_64", "--python-version", "3.11",
                        "--implementation", "cp", "--abi", "cp311", "-q", "-d", str(cache)], check=True)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != WHEEL_SHA256:
        raise SystemExit(f"{path}: sha256 {digest}, expected {WHEEL_SHA256}")
    return path


def make_sequences(wheel: Path, data: Path) -> list:
    """Write every photo's sequence under ``data/homography/<name>`` (kept if already there);
    returns the scene ids."""
    scenes = []
    with zipfile.ZipFile(wheel) as z:
        for index, photo in enumerate(tqdm(PHOTOS, desc="sequences", unit="scene")):
            name = photo.rsplit(".", 1)[0].replace("_", "-")
            scenes.append(f"homography/{name}")
            make_sequence(data / "homography" / name, functools.partial(_decode, z, f"skimage/data/{photo}"),
                          np.random.default_rng([SEED, index]))
    return scenes


def _decode(z: zipfile.ZipFile, member: str) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(z.read(member), np.uint8), cv2.IMREAD_UNCHANGED)


def montage(data: Path, scenes: list, path: Path, thumb=(96, 72)) -> None:
    """A JPEG of every sequence, one row of its views each, to see what was scored."""
    rows = [np.hstack([cv2.resize(cv2.imread(str(data / s / f"img{k}.png"), cv2.IMREAD_GRAYSCALE), thumb,
                                  interpolation=cv2.INTER_AREA) for k in range(1, 7)]) for s in scenes]
    cv2.imwrite(str(path), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 75])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="/tmp/real_gcn/unseen")
    ap.add_argument("--cache", default="/tmp/real_gcn/unseen/wheel")
    ap.add_argument("--detectors", default="orb,sift")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "orb_confirmation_part_b.md"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    data = Path(args.data)
    scenes = make_sequences(fetch_wheel(Path(args.cache)), data)
    pictures = Path(args.out).with_name("orb_confirmation_part_b.jpg")  # the same views every run
    montage(data, scenes, pictures)
    out = results_header("ORB confirmation, part B: homography sequences from unseen photographs", __file__, argv,
                         torch_threads=1) + [
        "Protocol: benchmarks/results/orb_confirmation_protocol.md (fixed before this run). Scenes: "
        f"{len(scenes)} sequences of 6 views from the scikit-image 0.25.2 photographs; 500 keypoints; "
        "windows of 3, 4, 6 consecutive views; labels by exact homography (true < 3 px, false > 10 px). "
        "Methods with default settings; gcn = the shipped model of the descriptor kind at its stored "
        f"threshold. The sequences, a row each: {pictures.name}.\n"]
    t0 = time.time()
    for det in args.detectors.split(","):
        folder = data / det
        folder.mkdir(parents=True, exist_ok=True)
        if not list(folder.glob("*.npz")):
            convert(data, folder, scenes, sizes=(3, 4, 6), detectors=(det,), max_features=500)
        problems = [load_problem(f) for f in sorted(folder.glob("*.npz"))]
        report = evaluate(problems, METHODS)
        out.append(f"\n## {det.upper()}: {len(problems)} problems\n")
        out.append(format_table(report))
        subsets = {s.split("/")[1]: [p.name for p in problems if p.name.startswith(s.replace("/", "_") + "_")]
                   for s in scenes}
        true_pairs = {p.name: count_pairs(p.gt_track, p.view_index)[1] for p in problems}
        # secondary (protocol addendum): windows whose labels hold >= 10 true pairs
        labelled = [n for n, c in true_pairs.items() if c >= 10]
        out.extend(lead_lines(report, problems, {">= 10 labelled true pairs": labelled}))
        out.append("\nPer scene, mean F1 (windows of that scene):\n")
        shown = [m for m, e in report["methods"].items() if not e.get("reference")]
        out.append("| scene | true pairs | " + " | ".join(report["methods"][m]["describe"] for m in shown) + " |")
        out.append("|---|---|" + "---|" * len(shown))
        for scene, names in subsets.items():
            cells = [np.mean([report["methods"][m]["per_problem"][n]["F1"] for n in names
                              if n in report["methods"][m]["per_problem"]]) for m in shown]
            out.append(f"| {scene} | {sum(true_pairs[n] for n in names)} | "
                       + " | ".join(f"{c:.3f}" for c in cells) + " |")
        print("\n".join(out[-len(subsets) - 8:]), flush=True)
    out.append(f"\nTotal wall time {time.time() - t0:.0f} s.")
    write_results(args.out, "\n".join(out) + "\n")


if __name__ == "__main__":
    main()
