"""Tests of gcn_match_ros.bags.contents: scene bags written and read back, their windows and labels."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from gcn_match_ros.bags import contents
from gcn_match_ros.windowing import WindowAssembler, WindowConfig

from conftest import BAG_CAMERAS as CAMS, assert_frames_equal, synthetic_frames


def in_stamp_order(frames_by_cam):
    return sorted((f for fs in frames_by_cam.values() for f in fs), key=lambda f: (f.stamp_ns, CAMS.index(f.camera_id)))


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


def test_window_labels_singletons_become_unmatched():
    np.testing.assert_array_equal(contents.window_labels(np.array([5, 5, 7, -1, -2, 9])), [5, 5, -1, -1, -2, -1])


def test_a_pose_that_is_none_is_a_bag_error_naming_its_message(tmp_path):
    frames, labels = synthetic_frames()
    bad = frames["cam1"][2]
    frames["cam1"][2] = dataclasses.replace(bad, t=np.array([0.0, np.nan, 1.0]))
    path = contents.write_scene_bag(tmp_path / "nan_pose.mcap", frames, labels, label_method="test")
    with pytest.raises(contents.BagError, match=r"malformed PoseStamped message on /cam1/pose at "
                                                 rf"{bad.stamp_ns / 1e9:.9f}: position \[.*nan.*\] is not finite"):
        contents.read_bag(path)
