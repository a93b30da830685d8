"""Tests of gcn_match_ros.bags.io: truncated or corrupt bags raise BagError; restamping raw messages."""
from __future__ import annotations

import re

import numpy as np
import pytest

from gcn_match_ros.bags import codec, contents, typesys
from gcn_match_ros.bags import io as bag_io
from gcn_match_ros.windowing import WindowConfig

from conftest import BAG_CAMERAS as CAMS, synthetic_frames


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
