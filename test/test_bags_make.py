"""Tests of gcn_match_ros.bags.make: the sample bags it made (bags/) hold the documented rig of cameras."""
from __future__ import annotations

import numpy as np
import pytest

from gcn_match_ros.bags import contents, typesys
from gcn_match_ros.windowing import WindowConfig

from conftest import BAG_CAMERAS as CAMS, SAMPLE_BAGS as BAGS, SHARED_DATA


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
