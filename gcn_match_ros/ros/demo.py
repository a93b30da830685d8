"""End-to-end demo: a sample bag replayed into the matcher node, every window scored.

``./run.sh demo`` (= ``python -m gcn_match_ros.ros.demo``):

1. starts the matcher node as its own process (``python -m gcn_match_ros.ros.matcher_node``,
   parameters as ROS arguments; default solver ``gcn`` with the model shipped in the
   package);
2. replays a sample bag from ``bags/`` with ``bag_play --restamp`` (stamps shifted to now,
   so latencies are real) — keypoint frames of 3 cameras and their ground-truth labels;
3. a scoring consumer in this process receives every ``MatchWindow`` and the replayed
   keypoints, takes each view's ground truth from the bag file (the labels of
   ``/<cam>/gt_labels``: scene-global point ids, read with :mod:`gcn_match_ros.bags`) and
   prints precision / recall / F1 of the tracks and the latency per window, then a summary
   (with the node's own drop counters from ``/diagnostics``);
4. draws the matches of every window across its views into ``out/demo_matches.png``
   (on the dataset images when ``../shared/data`` has them, else on blank canvases of the
   image size), stops the node with SIGINT and exits 0.

Everything stays on this machine (``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) on a
domain of its own (``ROS_DOMAIN_ID`` if set, else a random one).
"""
from __future__ import annotations

import argparse
import collections
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from gcn_match_msgs.msg import Keypoints, MatchWindow

from ..bags.contents import read_bag, window_labels
from ..bags.io import BagError
from ..data.scenes import DATA_ROOT
from ..landmark_map import LandmarkMap
from ..metrics import score_result
from ..paths import CHECKOUT
from ..plots import plot_landmark_map
from ..problem import Problem, Result
from ..rounding import relabel_tracks
from ..solvers.gcn import DEFAULT_CHECKPOINT
from ..stamps import stamp_to_ns
from ..stream import solve_stream
from ..track_image import draw_tracks
from .conversions import match_window_to_arrays
from .dds import local_session_env
from .matcher_node import create_solver
from .spin import stop_node_process
from .testing import RosSession, diagnostic_values

CAMERAS = ("cam0", "cam1", "cam2")
DEFAULT_BAG = "oxford_graf_sift.mcap"


def _bag_dirs() -> List[Path]:
    dirs = [CHECKOUT / "bags"]
    try:  # an installed package (colcon / ament): <prefix>/share/gcn_match_ros/bags
        from ament_index_python.packages import get_package_share_directory
        dirs.append(Path(get_package_share_directory("gcn_match_ros")) / "bags")
    except Exception:  # not on AMENT_PREFIX_PATH, or no ament_index_python
        pass
    dirs.append(Path(sys.prefix) / "share" / "gcn_match_ros" / "bags")
    return list(dict.fromkeys(dirs))


def _find_bag(name: str) -> Optional[Path]:
    p = Path(name)
    if p.exists():
        return p
    for d in _bag_dirs():
        if (d / name).exists():
            return d / name
    return None


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m gcn_match_ros.ros.demo", description=__doc__.split("\n\n")[0])
    p.add_argument("--bag", default=DEFAULT_BAG, help=f"bag file (path, or a name in bags/; default {DEFAULT_BAG})")
    p.add_argument("--solver", default="gcn", help="matching method, e.g. gcn, nn, spectral, 'nn:graph=mutual'")
    p.add_argument("--checkpoint", default="", help="GCN checkpoint (default: the model shipped in the package)")
    p.add_argument("--params-file", type=Path, default=None,
                   help="matcher parameter file (default: the package's config/matcher.yaml); the demo's own "
                        "settings (cameras of the bag, solver, reliable input) override it")
    p.add_argument("--rate", type=float, default=1.0, help="bag playback rate (default 1: real time)")
    p.add_argument("--out", type=Path, default=None, help="picture path (default out/demo_matches.png)")
    p.add_argument("--data-root", type=Path, default=DATA_ROOT,
                   help="dataset root holding the bag's images (for the picture)")
    p.add_argument("--startup-timeout", type=float, default=300.0,
                   help="give up when the matcher node is not up after this many seconds (its warm-up compiles "
                        "the solver once per checkout: minutes on a busy 2-core machine)")
    p.add_argument("--timeout", type=float, default=90.0,
                   help="give up when the replay and its scoring take longer than this many seconds")
    return p


def _log(text: str) -> None:
    print(text, flush=True)


# ---------------------------------------------------------------------------------------
# Scoring consumer (rclpy node in this process)
# ---------------------------------------------------------------------------------------
class _Collector:
    """Subscribes the matcher's output, the replayed keypoints and labels, and /diagnostics."""

    def __init__(self, domain_id: int, cameras) -> None:
        self.session = RosSession("demo_scorer", domain_id=domain_id)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.windows = self.session.collect(MatchWindow, "/matcher_node/matches", qos)
        # (camera, stamp ns) -> (Keypoints message, its index among the camera's frames)
        self.keypoints: Dict[Tuple[str, int], Tuple[object, int]] = {}
        self.per_camera = collections.Counter()
        self.diagnostics: List[dict] = []
        self.session.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, qos)
        for cam in cameras:
            self.session.node.create_subscription(Keypoints, f"/{cam}/keypoints", self._on_keypoints, qos)

    def _on_keypoints(self, msg) -> None:
        # Frames of one camera arrive in bag order (reliable, one publisher): the i-th message
        # of a camera is frame i of that camera in the bag, whatever the restamping did.
        self.keypoints[(str(msg.camera_id), stamp_to_ns(msg.header.stamp))] = (msg, self.per_camera[msg.camera_id])
        self.per_camera[msg.camera_id] += 1

    def _on_diag(self, msg) -> None:
        found = diagnostic_values(msg, "/matcher_node")
        if found is not None:
            self.diagnostics.append(found[1])

    def spin_until(self, cond, timeout: float) -> bool:
        return self.session.spin_until(cond, timeout)

    def close(self) -> None:
        self.session.close()


# ---------------------------------------------------------------------------------------
# Scoring and drawing
# ---------------------------------------------------------------------------------------
def score_window(msg, col: _Collector, contents) -> Optional[dict]:
    """P/R/F1 of one MatchWindow against the bag's ground-truth labels (scene-global point
    ids of each view's frame); None when a view's frame or labels are unknown."""
    w = match_window_to_arrays(msg)
    labels, kps, sources = [], [], []
    for cam, stamp in zip(w.camera_ids, msg.view_stamps):
        entry = col.keypoints.get((cam, stamp_to_ns(stamp)))
        if entry is None or entry[1] >= len(contents.labels.get(cam, [])):
            return None
        kp, index = entry
        lab = contents.labels[cam][index]
        if lab is None or len(lab) != int(kp.count):
            return None
        labels.append(np.asarray(lab, np.int64))
        kps.append(kp)
        sources.append(contents.sources[cam][index])
    gt = window_labels(np.concatenate(labels))
    if gt.shape[0] != w.n_keypoints:  # the node trimmed a frame (max_keypoints)
        return None
    n = w.n_keypoints
    problem = Problem(view_offsets=w.view_offsets,
                      keypoints=np.concatenate([np.frombuffer(k.keypoints, np.float32).reshape(-1, 2) for k in kps]),
                      descriptors=np.zeros((n, 1), np.float32), gt_track=gt)
    result = Result(track=w.track, pair_rows=w.pair_rows, pair_cols=w.pair_cols, pair_scores=w.pair_scores)
    s = score_result(problem, result)
    return {"P": s["P"], "R": s["R"], "F1": s["F1"], "AP": s["AP"], "arrays": w, "gt": gt,
            "keypoints": kps, "sources": sources, "true_pairs": s["true_pairs"]}


def offline_parity(windows: List[MatchWindow], problems: List[Problem], stamps: List[int], solver: str,
                   checkpoint: str) -> Tuple[int, int]:
    """(windows whose tracks and landmark ids equal the offline ones, windows compared): the
    bag's windows (``problems``, their newest ``stamps``) solved offline as one stream, in order,
    against the node's (the replay restamps the frames, so windows are paired by order; landmark
    ages are differences of stamps and ids do not depend on the shift)."""
    offline = solve_stream(create_solver(solver, checkpoint), problems, stamps)
    same = 0
    for msg, (result, landmarks) in zip(windows, offline):
        w = match_window_to_arrays(msg)
        same += bool(np.array_equal(relabel_tracks(result.track), w.track)
                     and w.landmark_ids is not None and np.array_equal(w.landmark_ids, landmarks.ids))
    return same, min(len(windows), len(problems))


def map_landmarks(windows: List[MatchWindow], problems: List[Problem], path: Path) -> Optional[str]:
    """With camera poses in the bag: the node's landmarks triangulated into a map
    (:class:`gcn_match_ros.landmark_map.LandmarkMap`), drawn with the camera path
    (:func:`gcn_match_ros.plots.plot_landmark_map`); returns a summary, or None without poses."""
    landmark_map, centers, span = LandmarkMap(), [], {}
    for k, (msg, problem) in enumerate(zip(windows, problems)):
        w = match_window_to_arrays(msg)
        if w.landmark_ids is None or problem.R is None or problem.K is None:
            return None
        landmark_map.add_window(w.landmark_ids, problem.keypoints, problem.view_index, problem.K, problem.R,
                                problem.t, w.stamp_ns)
        centers.append(-problem.R[0].T @ problem.t[0])
        for i in np.unique(w.landmark_ids[w.landmark_ids >= 0]).tolist():
            span.setdefault(i, [k, k])[1] = k
    if not span:
        return None
    ids, points, _ = landmark_map.arrays()
    lifetimes = np.array([span[i][1] - span[i][0] + 1 for i in ids.tolist()], np.int64)
    plot_landmark_map(points, lifetimes, np.array(centers), path,
                      title=f"{len(ids)} of {len(span)} landmarks mapped (camera 0's path in red)")
    all_life = np.array([e - s + 1 for s, e in span.values()])
    return (f"{len(span)} ids over {len(windows)} windows, {len(ids)} triangulated; windows per landmark: "
            f"median {np.median(all_life):.0f}, max {all_life.max()}")


def default_params_file() -> Optional[Path]:
    """config/matcher.yaml of this checkout, else of the installed package, else None."""
    here = CHECKOUT / "config" / "matcher.yaml"
    if here.is_file():
        return here
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        installed = Path(get_package_share_directory("gcn_match_ros")) / "config" / "matcher.yaml"
    except (ImportError, PackageNotFoundError, ValueError):
        return None
    return installed if installed.is_file() else None


def draw_windows(rows: List[dict], out: Path, data_root: Path, height: int = 260) -> str:
    """One row per window, its views side by side (:func:`gcn_match_ros.track_image.draw_tracks`);
    lines join consecutive keypoints of each track (green: same ground-truth point, red:
    different points, yellow: not labelled). Returns what the views are drawn on."""
    on_images = True
    row_imgs = []
    for k, r in enumerate(rows):
        w, gt = r["arrays"], r["gt"]
        images, sizes = [], []
        for kp, src in zip(r["keypoints"], r["sources"]):
            img = cv2.imread(str(data_root / src), cv2.IMREAD_GRAYSCALE) if src and (data_root / src).is_file() else None
            on_images &= img is not None
            images.append(img)
            sizes.append((int(kp.camera_info.width) or 640, int(kp.camera_info.height) or 480))
        counts = collections.Counter()

        def by_truth(t: int, a: int, b: int) -> tuple:
            kind = ("unlabelled" if gt[a] == -2 or gt[b] == -2 else
                    "correct" if gt[a] >= 0 and gt[a] == gt[b] else "wrong")
            counts[kind] += 1
            return {"unlabelled": (0, 200, 230), "correct": (60, 200, 60), "wrong": (40, 40, 230)}[kind]

        kps = [np.frombuffer(kp.keypoints, np.float32).reshape(-1, 2) for kp in r["keypoints"]]
        canvas = draw_tracks(images, kps, w.track, image_sizes=sizes, height=height, link_color=by_truth)
        names = " | ".join(f"{c}: {Path(s).name or '?'}" for c, s in zip(w.camera_ids, r["sources"]))
        title = (f"window {k + 1}  P {r['P']:.2f}  R {r['R']:.2f}  F1 {r['F1']:.2f}   lines: "
                 f"{counts['correct']} correct, {counts['wrong']} wrong, {counts['unlabelled']} unlabelled   ({names})")
        cv2.putText(canvas, title, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        row_imgs.append(canvas)
    width = max(r.shape[1] for r in row_imgs)
    what = "dataset images" if on_images else "blank canvases of the image size (images not found)"
    footer = np.full((28, width, 3), 255, np.uint8)
    cv2.putText(footer, f"{rows[0]['arrays'].method}: tracks drawn on {what}; green = same ground-truth point, "
                        f"red = different points, yellow = not labelled", (4, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.42,
                (0, 0, 0), 1, cv2.LINE_AA)
    padded = [np.pad(r, ((0, 6), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in row_imgs]
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), np.vstack(padded + [footer])):
        raise OSError(f"cannot write {out}")
    return what


# ---------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------
def _check_model(solver: str, checkpoint: str) -> Optional[str]:
    """A clear message when the gcn solver's model is missing, else None."""
    if not solver.split(":")[0].strip() == "gcn":
        return None
    path = Path(checkpoint) if checkpoint else Path(DEFAULT_CHECKPOINT)
    if not path.is_file():
        which = "the checkpoint" if checkpoint else "the model shipped in the package"
        return (f"{which} {path} is missing, so the gcn solver cannot start. Train one (see "
                f"gcn_match_ros/models/README.md: benchmarks/train_default.py) or pass --checkpoint FILE; "
                f"--solver nn runs the demo with the nearest-neighbour baseline instead")
    return None


def _percentile(values, q) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    t_start = time.monotonic()
    problem = _check_model(args.solver, args.checkpoint)
    if problem:
        _log(f"demo: error: {problem}")
        return 1
    bag = _find_bag(args.bag)
    if bag is None:
        _log(f"demo: error: bag '{args.bag}' not found (looked in {', '.join(str(d) for d in _bag_dirs())})")
        return 1
    try:
        contents = read_bag(bag, progress=False)
    except BagError as exc:
        _log(f"demo: error: {exc}")
        return 1
    cameras = tuple(contents.cameras)
    # the windows the node will form on replay, formed once here (scoring, offline parity, the map)
    replay = contents.replay_windows()
    expected = len(replay.problems)
    _log(f"demo: {bag.name}: {contents.n_frames} frames of {len(cameras)} cameras ({', '.join(cameras)}), "
         f"{expected} windows; solver {args.solver}")

    # the large segment: bag_play publishes 3 cameras' ~200 KB frames at once (see gcn_match_ros.ros)
    env, domain = local_session_env("gcn_match_ros-demo-roslog-")
    env["PYTHONUNBUFFERED"] = "1"
    out = args.out or ((CHECKOUT / "out") if (CHECKOUT / "setup.py").is_file() else Path.cwd() / "out") / "demo_matches.png"
    node_log = out.parent / "demo_matcher_node.log"
    out.parent.mkdir(parents=True, exist_ok=True)

    params_file = args.params_file or default_params_file()
    cmd = [sys.executable, "-m", "gcn_match_ros.ros.matcher_node", "--ros-args"]
    if params_file is not None:
        cmd += ["--params-file", str(params_file)]
    cmd += ["-p", f"cameras:=[{','.join(cameras)}]", "-p", f"solver:={args.solver}",
           "-p", "diagnostics_period:=0.5",
           # The replay is reliable and should be scored whole: best-effort (sensor_data) input
           # can lose a fragmented ~200 KB Keypoints message now and then.
           "-p", "input_qos:=reliable"]
    if args.checkpoint:
        cmd += ["-p", f"checkpoint:={args.checkpoint}"]
    _log(f"demo: starting the matcher node (parameters: {params_file or 'defaults'} + the demo's; "
         f"ROS_DOMAIN_ID={domain}, log: {node_log})")
    log_fh = open(node_log, "w")
    node = subprocess.Popen(cmd, env=env, stdout=log_fh, stderr=subprocess.STDOUT, cwd=CHECKOUT)
    col = None
    player = None
    try:
        col = _Collector(domain, cameras)
        deadline = t_start + args.startup_timeout
        up = col.spin_until(lambda: node.poll() is not None or col.session.node.count_publishers("/matcher_node/matches") > 0,
                            timeout=max(1.0, deadline - time.monotonic()))
        if node.poll() is not None or not up:
            log_fh.flush()
            _log(f"demo: error: the matcher node did not start (exit {node.poll()}); its log:\n"
                 + node_log.read_text()[-3000:])
            return 1
        _log(f"demo: matcher node up after {time.monotonic() - t_start:.1f} s; replaying {bag.name} "
             f"(rate {args.rate:g}, stamps shifted to now)")
        deadline = time.monotonic() + args.timeout
        # Keypoints only (labels come from the bag file); each topic has two subscribers: the
        # node and the scorer here, and bag_play waits until both are matched.
        topics = [f"/{c}/keypoints" for c in cameras]
        player = subprocess.Popen([sys.executable, "-m", "gcn_match_ros.ros.bag_play", str(bag), "--restamp",
                                   "--rate", str(args.rate), "--quiet", "--topics", *topics,
                                   "--wait-for-subscribers", "2", "--wait-for-all-acked", "3"],
                                  env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=CHECKOUT)
        player_out: List[str] = []
        reader = threading.Thread(target=lambda: player_out.extend(player.stdout), daemon=True)
        reader.start()
        col.spin_until(lambda: player.poll() is not None, timeout=max(1.0, deadline - time.monotonic()))
        if player.poll() is None or player.returncode != 0:
            _log(f"demo: error: bag_play failed (exit {player.poll()}):\n{''.join(player_out)[-2000:]}")
            return 1
        col.spin_until(lambda: len(col.windows) >= expected, timeout=min(15.0, max(1.0, deadline - time.monotonic())))
        # One more node report, so its counters include the last window.
        n_diag = len(col.diagnostics)
        col.spin_until(lambda: len(col.diagnostics) > n_diag, timeout=3.0)
    finally:
        if player is not None and player.poll() is None:
            player.terminate()
        stop_node_process(node, timeout=15)
        log_fh.close()
        if col is not None:
            col.close()

    # -- report -----------------------------------------------------------------------------
    rows = []
    _log("")
    _log(f"{'window':>6} {'views':>5} {'keypoints':>9} {'tracks':>6} {'P':>6} {'R':>6} {'F1':>6} "
         f"{'latency':>9} {'compute':>9}")
    for k, msg in enumerate(col.windows):
        r = score_window(msg, col, contents)
        w = r["arrays"] if r else None
        lat_ms = 1e3 * msg.latency_seconds
        if r is None:
            _log(f"{k + 1:>6}  (no ground truth received for this window)")
            continue
        r.update(latency=msg.latency_seconds, compute=msg.total_seconds)
        rows.append(r)
        _log(f"{k + 1:>6} {w.n_views:>5} {w.n_keypoints:>9} {w.track_count:>6} {r['P']:>6.3f} {r['R']:>6.3f} "
             f"{r['F1']:>6.3f} {lat_ms:>6.1f} ms {1e3 * msg.total_seconds:>6.1f} ms")
    diag = col.diagnostics[-1] if col.diagnostics else {}
    drops = {k: v for k, v in diag.items() if k.startswith(("frames dropped ", "windows dropped ")) and v != "0"}
    _log("")
    if not rows:
        _log(f"demo: error: no scored window received ({len(col.windows)} windows, {expected} expected); "
             f"node log: {node_log}")
        return 1
    lat = [r["latency"] for r in rows]
    method = rows[0]["arrays"].method
    _log(f"summary ({method} on {bag.name}): {len(rows)}/{expected} windows scored; "
         f"mean P {np.mean([r['P'] for r in rows]):.3f}, R {np.mean([r['R'] for r in rows]):.3f}, "
         f"F1 {np.mean([r['F1'] for r in rows]):.3f}")
    _log(f"  latency (newest view stamp -> published) p50 {1e3 * _percentile(lat, 50):.1f} ms, "
         f"p95 {1e3 * _percentile(lat, 95):.1f} ms; compute p50 "
         f"{1e3 * _percentile([r['compute'] for r in rows], 50):.1f} ms")
    received = ", ".join(f"{c} {diag.get(f'frames received {c}', '?')}" for c in cameras)
    _log(f"  node diagnostics: frames received {received}; {diag.get('windows published', '?')} windows "
         f"published, drops: "
         f"{', '.join(f'{k} = {v}' for k, v in drops.items()) or 'none'}")
    problems = replay.problems
    same, total = offline_parity(col.windows, problems, replay.stamps_ns,
                                 args.solver, args.checkpoint)
    _log(f"  offline (the bag's windows solved as one stream, gcn_match_ros.stream.solve_stream): tracks and "
         f"landmark ids identical to the node's in {same}/{total} windows")
    what = draw_windows(rows, out, args.data_root)
    _log(f"  picture: {out} (tracks drawn on {what})")
    stem = out.stem.replace("matches", "landmarks") if "matches" in out.stem else out.stem + "_landmarks"
    landmarks_png = out.with_name(stem + out.suffix)
    mapped = map_landmarks(col.windows, problems, landmarks_png)
    if mapped:
        _log(f"  landmarks: {mapped}; picture: {landmarks_png}")
    _log(f"  node exit status {node.returncode}; demo took {time.monotonic() - t_start:.1f} s")
    if node.returncode != 0:
        _log(f"demo: error: the matcher node exited with {node.returncode}; log: {node_log}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
