"""Tests of gcn_match_ros.ros.bag_play and gcn_match_ros.ros.bag_record: a bag played and recorded through DDS."""
# The tools run as subprocesses, each with its own rclpy context, on a domain id of their own,
# discovery confined to this machine.
from __future__ import annotations

import dataclasses
import os
import random
import signal
import subprocess
import sys

import numpy as np
import pytest

from gcn_match_ros.bags import contents, typesys
from gcn_match_ros.bags import io as bag_io

from conftest import BAG_CAMERAS as CAMS, SAMPLE_BAGS as BAGS, assert_frames_equal


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
    # the timeout is the check that it does not hang on the cut record
    p = subprocess.run(_tool("bag_play", cut), env=ros_env, capture_output=True, text=True, timeout=30)
    assert p.returncode == 1
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("bag_play: error:") and str(cut) in lines[0], p.stderr
    assert "Traceback" not in p.stderr


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
