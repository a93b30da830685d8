"""Tests of gcn_match_ros.ros.demo (what ./run.sh demo runs): the sample bag replayed into the matcher node, scored."""
import os
import re
import subprocess
import sys
from pathlib import Path

import cv2

from conftest import domain_id

REPO = Path(__file__).resolve().parents[1]
SUMMARY = re.compile(r"^summary \((?P<method>[^)]*) on oxford_graf_sift\.mcap\): (?P<scored>\d+)/(?P<expected>\d+) "
                     r"windows scored; mean P (?P<P>[\d.]+), R (?P<R>[\d.]+), F1 (?P<F1>[\d.]+)$", re.MULTILINE)


def run_demo(tmp_path, *args):
    """(exit status, output) of ``python -m gcn_match_ros.ros.demo --out <tmp>/m.png ARGS`` on a domain of
    its own, discovery on this machine only, temporary files under ``tmp_path``."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(domain_id()),
               TMPDIR=str(tmp_path))
    env.pop("ROS_LOCALHOST_ONLY", None)
    proc = subprocess.run([sys.executable, "-m", "gcn_match_ros.ros.demo", "--out", str(tmp_path / "m.png"), *args],
                          cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=120)
    return proc.returncode, proc.stdout


def check_run(tmp_path, rc, out, method):
    """The demo ran to the end: every window scored, no drops, the picture drawn; returns the summary."""
    assert rc == 0, out
    summary = SUMMARY.search(out)
    assert summary, out
    assert summary["method"] == method
    assert (summary["scored"], summary["expected"]) == ("4", "4") and "4/4 windows scored" in out
    assert "node diagnostics: frames received cam0 4, cam1 4, cam2 4; 4 windows published, drops: none" in out, out
    assert "node exit status 0" in out
    # the node's tracks and landmark ids are what the bag solved offline as one stream gives
    assert "tracks and landmark ids identical to the node's in 4/4 windows" in out, out
    picture = tmp_path / "m.png"
    assert f"picture: {picture}" in out
    img = cv2.imread(str(picture))
    assert img is not None and img.shape[0] > 4 * 260 and img.shape[1] > 300  # 4 windows of 3 views, one per row
    assert (tmp_path / "demo_matcher_node.log").is_file()
    return {k: float(summary[k]) for k in ("P", "R", "F1")}


def test_demo_with_the_shipped_gcn_model(tmp_path):
    rc, out = run_demo(tmp_path)
    scores = check_run(tmp_path, rc, out, "gcn:model=shipped")
    assert scores["F1"] >= 0.9, out


def test_demo_with_the_nearest_neighbour_baseline(tmp_path):
    rc, out = run_demo(tmp_path, "--solver", "nn")
    scores = check_run(tmp_path, rc, out, "nn")
    assert scores["P"] >= 0.8 and scores["F1"] >= 0.6, out  # mutual NN: precise, recall lower than gcn's


def test_demo_on_a_bag_with_poses_maps_the_landmarks(tmp_path):
    rc, out = run_demo(tmp_path, "--bag", "strecha_fountain_sift.mcap")
    assert rc == 0, out
    assert "tracks and landmark ids identical to the node's in 9/9 windows" in out, out
    found = re.search(r"landmarks: (\d+) ids over 9 windows, (\d+) triangulated; windows per landmark: median (\d+)", out)
    assert found and int(found[2]) > 100 and int(found[3]) >= 2, out  # points live across windows
    img = cv2.imread(str(tmp_path / "m_landmarks.png"))
    assert img is not None and img.shape[1] > 600


def test_a_matcher_node_not_up_in_its_start_up_time_is_a_clear_error(tmp_path):
    # the start-up budget is the node's own (its warm-up compiles the solver once per checkout);
    # the replay has --timeout of its own after it
    rc, out = run_demo(tmp_path, "--solver", "nn", "--startup-timeout", "0")
    assert rc == 1, out
    assert "the matcher node did not start" in out
