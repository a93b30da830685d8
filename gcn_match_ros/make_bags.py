"""Make the sample bags (``bags/``) from the dataset scenes in ``shared/data``.

    python -m gcn_match_ros.make_bags --out bags/
    python -m gcn_match_ros.make_bags --out /tmp/b --scenes oxford/boat strecha/castle-P19 \\
        --detector orb --cameras 4 --force

Each scene becomes ``<out>/<dataset>_<scene>_<detector>.mcap`` (the scene name up to its
first '-', e.g. ``strecha_fountain_sift.mcap`` from ``strecha/fountain-P11``): a rig of
``--cameras`` cameras sliding along the scene's images, one synchronised capture per
time step (layout and design: :mod:`gcn_match_ros.bags`). Output is deterministic for a
given OpenCV build: rerunning gives the same messages.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional, Sequence

from tqdm import tqdm

from . import bags

DEFAULT_SCENES = ("oxford/graf", "strecha/fountain-P11")
DEFAULT_DATA_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data"


def bag_name(scene: str, detector: str) -> str:
    """``oxford/graf`` -> ``oxford_graf_<detector>.mcap``; ``strecha/fountain-P11`` ->
    ``strecha_fountain_<detector>.mcap``; ``middlebury_temple`` -> ``middlebury_temple_<detector>.mcap``."""
    parts = [p.split("-")[0] for p in Path(scene).parts]
    return "_".join(parts + [detector]).lower() + ".mcap"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m gcn_match_ros.make_bags", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT, help="shared/data")
    p.add_argument("--scenes", nargs="+", default=list(DEFAULT_SCENES),
                   help=f"scene ids under --data-root (default: {' '.join(DEFAULT_SCENES)})")
    p.add_argument("--detector", choices=("sift", "orb"), default="sift")
    p.add_argument("--max-features", type=int, default=500, help="per image, before de-duplication")
    p.add_argument("--cameras", type=int, default=3, help="cameras of the rig (views per window)")
    p.add_argument("--rate", type=float, default=2.0, help="rig captures per second")
    p.add_argument("--stagger", type=float, default=0.002, help="camera j is stamped j * STAGGER s later")
    p.add_argument("--storage", choices=bags.STORAGES, default="mcap",
                   help="mcap: single .mcap files; sqlite3: rosbag2 directories")
    p.add_argument("--force", action="store_true", help="replace existing bags")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    from . import datasets

    args.out.mkdir(parents=True, exist_ok=True)
    written = []
    for scene in tqdm(args.scenes, desc="bags", unit="bag", disable=args.quiet or len(args.scenes) < 2):
        name = bag_name(scene, args.detector)
        if args.storage != "mcap":
            name = name[:-len(".mcap")]
        path = args.out / name
        if path.exists():
            if not args.force:
                print(f"make_bags: error: {path} exists (use --force to replace it)", file=sys.stderr)
                return 1
            if path.is_dir():
                import shutil

                shutil.rmtree(path)
            else:
                path.unlink()
        try:
            bags.convert_scene_to_bag(args.data_root, scene, path, n_cameras=args.cameras,
                                      detector=args.detector, max_features=args.max_features,
                                      rate_hz=args.rate, stagger=args.stagger, storage=args.storage,
                                      progress=not args.quiet)
        except (datasets.DatasetError, ValueError) as exc:
            print(f"make_bags: error: {scene}: {exc}", file=sys.stderr)
            return 1
        written.append(path)
    for path in written:
        info = bags.bag_info(path)
        size = path.stat().st_size if path.is_file() else sum(f.stat().st_size for f in path.rglob("*"))
        frames = sum(n for t, n in info.counts.items() if info.topics[t] == bags.KEYPOINTS_TYPE)
        print(f"{path}: {size / 1e6:.2f} MB, {frames} frames, {info.message_count} messages, "
              f"{len(info.topics)} topics, {(info.end_ns - info.start_ns) * 1e-9:.3f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
