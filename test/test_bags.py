"""Bags: write/read round trip, windows, truncation, pose convention, the sample bags, and
bag_play -> bag_record through live DDS (subprocesses, each with its own rclpy context,
on a domain id of its own, discovery confined to this machine)."""
from __future__ import annotations

import dataclasses
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros import geometry
from gcn_match_ros.bags import codec, contents, typesys
from gcn_match_ros.bags import io as bag_io
from gcn_match_ros.windowing import Frame, WindowAssembler, WindowConfig

REPO = Path(__file__).resolve().parents[1]
BAGS = REPO / "bags"
SHARED_DATA = REPO.parent / "shared" / "data"
CAMS = ("cam0", "cam1", "cam2")


def _rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def synthetic_frames(steps: int = 5, dim: int = 8, seed: int = 0, skip=((3, "cam2"),)):
    """CAMS x steps frames (camera j stamped 2 ms after camera 0), random sizes, scores,
    poses and K on cam0/cam1 (cam2 uncalibrated, no pose); scene-global labels."""
    rng = np.random.default_rng(seed)
    frames = {c: [] for c in CAMS}
    labels = {c: [] for c in CAMS}
    for k in range(steps):
        for j, cam in enumerate(CAMS):
            if (k, cam) in skip:
                continue
            n = int(rng.integers(5, 40))
            calibrated = cam != "cam2"
            K = np.array([[500.0 + j, 0, 320], [0, 501.0, 240], [0, 0, 1]]) if calibrated else None
            frames[cam].append(Frame(
                camera_id=cam, stamp_ns=1_700_000_000 * 10**9 + k * 10**8 + j * 2 * 10**6,
                keypoints=rng.uniform(0, 600, (n, 2)).astype(np.float32),
                descriptors=rng.normal(size=(n, dim)).astype(np.float32), frame_id=f"{cam}_optical_frame",
                scales=rng.uniform(1, 9, n).astype(np.float32),
                orientations=rng.uniform(-3, 3, n).astype(np.float32),
                scores=rng.uniform(0, 1, n).astype(np.float32), K=K,
                image_size=(640, 480) if calibrated else None,
                R=_rotation(rng) if calibrated else None, t=rng.normal(size=3) if calibrated else None))
            labels[cam].append(rng.integers(-2, 30, n))
    return frames, labels


def assert_frames_equal(a: Frame, b: Frame, poses: bool = True) -> None:
    assert (a.camera_id, a.stamp_ns, a.frame_id, a.image_size, a.binary) == \
        (b.camera_id, b.stamp_ns, b.frame_id, b.image_size, b.binary)
    for name in ("keypoints", "descriptors", "scales", "orientations", "scores", "K"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)
    if poses:
        for name in ("R", "t"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None), name
            if x is not None:
                np.testing.assert_allclose(x, y, atol=1e-12, err_msg=name)


def in_stamp_order(frames_by_cam):
    return sorted((f for fs in frames_by_cam.values() for f in fs), key=lambda f: (f.stamp_ns, CAMS.index(f.camera_id)))


def test_typestore_matches_installed_messages():
    store = typesys.typestore()
    T = store.types[typesys.LABELS_TYPE]
    assert (T.UNMATCHED, T.UNLABELLED) == (-1, -2)
    for name in typesys.OUR_TYPES:  # a stale message build would decode bags differently
        src = (REPO / "msg_defs" / "msg" / f"{name}.msg").read_text()
        assert typesys.find_msg_file(f"gcn_match_msgs/msg/{name}").read_text() == src, \
            f"installed {name}.msg differs from msg_defs/: run ./run.sh setup"


@pytest.mark.parametrize("storage, name", [("mcap", "scene.mcap"), ("sqlite3", "scene_db")])
def test_round_trip_frames_labels_windows(tmp_path, storage, name):
    frames, labels = synthetic_frames()
    path = contents.write_scene_bag(tmp_path / name, frames, labels, storage=storage, label_method="test")
    assert path.is_file() == (storage == "mcap")
    c = contents.read_bag(path)
    assert c.cameras == list(CAMS)
    assert {t for t in c.topics} == {f"/{cam}/{x}" for cam in CAMS for x in ("keypoints", "camera_info", "gt_labels")} \
        | {"/cam0/pose", "/cam1/pose"}
    for cam in CAMS:
        assert len(c.frames[cam]) == len(frames[cam])
        for a, b, la, lb in zip(c.frames[cam], frames[cam], c.labels[cam], labels[cam]):
            assert_frames_equal(a, b)
            np.testing.assert_array_equal(la, lb)
    assert [c.frames[cam][i].stamp_ns for cam, i in c.order] == [f.stamp_ns for f in in_stamp_order(frames)]

    # windows: the bag's, and an assembler fed the original frames directly (as the node would)
    label_of = {(f.camera_id, f.stamp_ns): l for cam in CAMS for f, l in zip(frames[cam], labels[cam])}
    for config in (WindowConfig(cameras=CAMS), WindowConfig(cameras=CAMS, max_keypoints=12, min_views=2)):
        direct = WindowAssembler(dataclasses.replace(config, descriptor_dim=8))
        expected = [w for f in in_stamp_order(frames) for w in direct.add(f)] + direct.flush()
        got = list(contents.bag_windows(path, config))
        assert len(got) == len(expected) == 5
        assert [len(w) for w, _ in got] == [3, 3, 3, 2, 3]  # step 3 has no cam2 frame
        for (wa, la), wb in zip(got, expected):
            for a, b in zip(wa, wb):
                assert_frames_equal(a, b)
            parts = []
            for f in wb:
                orig = next(o for o in frames[f.camera_id] if o.stamp_ns == f.stamp_ns)
                keep = np.arange(orig.count)
                if orig.count > config.max_keypoints:
                    keep = np.sort(np.argsort(-orig.scores, kind="stable")[:config.max_keypoints])
                parts.append(label_of[(f.camera_id, f.stamp_ns)][keep])
            np.testing.assert_array_equal(la, np.concatenate(parts))


def test_binary_descriptors_and_uncalibrated_round_trip():
    rng = np.random.default_rng(1)
    bits = rng.integers(0, 2, (7, 256)).astype(np.float32)
    f = Frame(camera_id="cam0", stamp_ns=12_500_000_000, keypoints=rng.uniform(0, 9, (7, 2)).astype(np.float32),
              descriptors=bits, frame_id="cam0_optical_frame", binary=True, descriptor_name="orb")
    store = typesys.typestore()
    msg = codec.keypoints_msg(f)
    assert msg.descriptor_type == 1 and len(msg.descriptors_binary) == 7 * 32 and len(msg.descriptors) == 0
    back = codec.frame_from_keypoints_msg(store.deserialize_cdr(store.serialize_cdr(msg, typesys.KEYPOINTS_TYPE),
                                                               typesys.KEYPOINTS_TYPE))
    assert_frames_equal(back, f)
    assert back.K is None and back.image_size is None and back.scales is None


def test_window_labels_singletons_become_unmatched():
    np.testing.assert_array_equal(contents.window_labels(np.array([5, 5, 7, -1, -2, 9])), [5, 5, -1, -1, -2, -1])


def test_pose_convention_round_trip():
    rng = np.random.default_rng(2)
    for _ in range(50):
        R, t = _rotation(rng), rng.normal(size=3) * 5
        C, q = geometry.rt_to_pose(R, t)
        np.testing.assert_allclose(R @ C + t, 0, atol=1e-12)  # position is the camera centre
        R_wc = geometry.quat_to_matrix(q)
        np.testing.assert_allclose(R_wc, R.T, atol=1e-12)  # orientation is camera->world
        np.testing.assert_allclose(R_wc @ [0, 0, 1], R[2], atol=1e-12)  # optical axis in world
        R2, t2 = geometry.pose_to_rt(C, q)
        np.testing.assert_allclose(R2, R, atol=1e-12)
        np.testing.assert_allclose(t2, t, atol=1e-12)
    for R in (np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        np.testing.assert_allclose(geometry.quat_to_matrix(geometry.matrix_to_quat(R)), R, atol=1e-12)


def test_truncated_or_corrupt_bag_raises_bag_error(tmp_path):
    frames, labels = synthetic_frames(steps=3)
    path = contents.write_scene_bag(tmp_path / "ok.mcap", frames, labels)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    for call in (contents.read_bag, bag_io.bag_info, lambda p: list(contents.bag_windows(p, WindowConfig(cameras=CAMS)))):
        with pytest.raises(bag_io.BagError, match=re.escape(str(cut))):
            call(cut)
    with pytest.raises(bag_io.BagError, match="no such bag"):
        contents.read_bag(tmp_path / "missing.mcap")
    # intact index, damaged chunk data: fails mid-way, still a BagError naming the file
    bad = tmp_path / "bad.mcap"
    mid = bytearray(data)
    mid[len(data) // 3: len(data) // 3 + 64] = b"\xff" * 64
    bad.write_bytes(bytes(mid))
    with pytest.raises(bag_io.BagError, match=re.escape(str(bad))):
        contents.read_bag(bad)
    assert issubclass(bag_io.BagError, ValueError)


def test_restamp_cdr_shifts_header_only():
    store = typesys.typestore()
    frames, _ = synthetic_frames(steps=1)
    msg = codec.keypoints_msg(frames["cam0"][0])
    raw = bytes(store.serialize_cdr(msg, typesys.KEYPOINTS_TYPE))
    out = store.deserialize_cdr(bag_io.restamp_cdr(raw, 1_500_000_000), typesys.KEYPOINTS_TYPE)
    shifted = out.header.stamp.sec * 10**9 + out.header.stamp.nanosec
    assert shifted == frames["cam0"][0].stamp_ns + 1_500_000_000
    np.testing.assert_array_equal(out.keypoints, msg.keypoints)
    assert typesys.has_header(typesys.KEYPOINTS_TYPE) and typesys.has_header(typesys.POSE_TYPE)
    assert not typesys.has_header("geometry_msgs/msg/Pose") and not typesys.has_header("no_such_pkg/msg/Nothing")


# --------------------------------------------------------------------------------------
# Sample bags
# --------------------------------------------------------------------------------------
SAMPLES = {"oxford_graf_sift.mcap": ("oxford/graf", False),
           "strecha_fountain_sift.mcap": ("strecha/fountain-P11", True),
           "oxford_boat_orb.mcap": ("oxford/boat", False)}


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_sample_bags_load_with_documented_topics(name):
    path = BAGS / name
    assert path.is_file(), f"missing sample bag {path} (gcn-match make-bags --out bags/)"
    assert path.stat().st_size < 5e6
    assert name in (BAGS / "README.md").read_text()
    scene, has_poses = SAMPLES[name]
    c = contents.read_bag(path)
    per_cam = ("keypoints", "camera_info", "gt_labels") + (("pose",) if has_poses else ())
    assert set(c.topics) == {f"/{cam}/{x}" for cam in CAMS for x in per_cam}
    assert c.topics["/cam0/keypoints"] == typesys.KEYPOINTS_TYPE and c.topics["/cam0/gt_labels"] == typesys.LABELS_TYPE
    assert c.topics["/cam0/camera_info"] == typesys.CAMERA_INFO_TYPE
    n_images = len(set(s for cam in CAMS for s in c.sources[cam]))
    windows = list(c.windows(WindowConfig(cameras=CAMS)))
    assert len(windows) == n_images - len(CAMS) + 1 and all(len(w) == 3 and l is not None for w, l in windows)
    # the rig slides: step k, camera j sees image k + j; one image = same keypoints, same labels
    seen = {}
    for cam in CAMS:
        for f, lab, src in zip(c.frames[cam], c.labels[cam], c.sources[cam]):
            assert src.startswith(scene + "/") and f.frame_id == f"{cam}_optical_frame"
            assert (f.R is not None) == has_poses and (f.K is not None) == has_poses
            if src in seen:
                np.testing.assert_array_equal(seen[src][0].keypoints, f.keypoints)
                np.testing.assert_array_equal(seen[src][1], lab)
            seen[src] = (f, lab)
    if has_poses:  # poses round-trip to the dataset's world->camera R, t
        from gcn_match_ros.data import scenes as datasets
        sc = datasets.load_scene(SHARED_DATA, scene)
        for src, (f, _) in seen.items():
            v = [str(p.relative_to(SHARED_DATA)) for p in sc.image_paths].index(src)
            # a quaternion re-orthonormalises R (the .cam files print 6 decimals)
            np.testing.assert_allclose(f.R, sc.R[v], atol=1e-5)
            np.testing.assert_allclose(f.t, sc.t[v], atol=1e-5)
            np.testing.assert_allclose(f.R @ f.R.T, np.eye(3), atol=1e-12)
            np.testing.assert_allclose(f.K, sc.K[v])


# --------------------------------------------------------------------------------------
# bag_play -> bag_record through live DDS
# --------------------------------------------------------------------------------------
@pytest.fixture
def ros_env(tmp_path):
    env = dict(os.environ)
    parent = env.get("ROS_DOMAIN_ID")
    env["ROS_DOMAIN_ID"] = str(random.choice([d for d in range(1, 101) if str(d) != parent]))
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    env["ROS_LOG_DIR"] = str(tmp_path / "roslog")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _tool(name, *args):
    return [sys.executable, "-m", f"gcn_match_ros.ros.{name}", *map(str, args)]


def _decoded_equal(a, b) -> bool:
    if dataclasses.is_dataclass(a):
        return type(a).__name__ == type(b).__name__ and all(
            _decoded_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_decoded_equal(x, y) for x, y in zip(a, b))
    return a == b


@pytest.mark.timeout(60)
def test_play_record_round_trip_through_dds(tmp_path, ros_env):
    src = BAGS / "strecha_fountain_sift.mcap"
    topics = [f"/{cam}/{x}" for cam in CAMS[:2] for x in ("keypoints", "camera_info", "pose", "gt_labels")]
    out = tmp_path / "recorded.mcap"
    rec = subprocess.Popen(_tool("bag_record", "-o", out, "--topics", *topics), env=ros_env,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        play = subprocess.run(_tool("bag_play", src, "--rate", 8, "--topics", *topics, "--quiet",
                                    "--wait-for-subscribers", 1, "--wait-timeout", 30,
                                    # the recorder has everything before it is stopped (loaded CI)
                                    "--wait-for-all-acked", 10),
                              env=ros_env, capture_output=True, text=True, timeout=55)
        assert play.returncode == 0, play.stdout + play.stderr
        assert "done: 72 messages" in play.stderr + play.stdout
        rec.send_signal(signal.SIGTERM)  # finalises the bag
        rec_out, _ = rec.communicate(timeout=15)
    finally:
        if rec.poll() is None:
            rec.kill()
    assert rec.returncode == 0, rec_out
    assert out.is_file(), rec_out

    info = bag_io.bag_info(out)
    assert info.topics == {t: bag_io.bag_info(src).topics[t] for t in topics}
    assert all(info.counts[t] == 9 for t in topics), (info.counts, rec_out)
    # decoded fields equal, message by message, in order
    orig = {t: [] for t in topics}
    got = {t: [] for t in topics}
    store = typesys.typestore()
    for which, path in ((orig, src), (got, out)):
        for topic, msgtype, _, raw in bag_io.iter_raw(path, topics):
            which[topic].append(store.deserialize_cdr(raw, msgtype))
    for t in topics:
        assert all(_decoded_equal(a, b) for a, b in zip(orig[t], got[t])), t
    # and the frames/labels/poses the trainer sees
    a, b = contents.read_bag(src), contents.read_bag(out)
    for cam in CAMS[:2]:
        for fa, fb, la, lb in zip(a.frames[cam], b.frames[cam], a.labels[cam], b.labels[cam]):
            assert_frames_equal(fa, fb)
            np.testing.assert_array_equal(la, lb)


def test_play_truncated_bag_fails_with_one_line(tmp_path, ros_env):
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((BAGS / "oxford_graf_sift.mcap").read_bytes()[:100_000])
    t0 = time.monotonic()
    p = subprocess.run(_tool("bag_play", cut), env=ros_env, capture_output=True, text=True, timeout=30)
    assert p.returncode == 1
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("bag_play: error:") and str(cut) in lines[0], p.stderr
    assert "Traceback" not in p.stderr and time.monotonic() - t0 < 20


@pytest.mark.timeout(30)
def test_play_stops_cleanly_on_ctrl_c(ros_env):
    p = subprocess.Popen(_tool("bag_play", BAGS / "oxford_boat_orb.mcap", "--loop", "--restamp", "--quiet"),
                         env=ros_env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        lines = []
        for line in p.stderr:  # the node logs "playing ..." once publishing starts
            lines.append(line)
            if "playing" in line:
                break
        p.send_signal(signal.SIGINT)
        rest = p.stderr.read()
        assert p.wait(timeout=10) == 0
    finally:
        if p.poll() is None:
            p.kill()
    out = "".join(lines) + rest
    assert "interrupted after" in out and "Traceback" not in out, out
