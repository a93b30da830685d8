"""Tests of gcn_match_ros.data.convert: problems from scenes, window sampling, names, conversion end to end."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros.data.convert import convert, make_problem, problem_name, sample_windows
from gcn_match_ros.data.scenes import DatasetError, load_scene
from gcn_match_ros.problem import load_problem

from conftest import (REFERENCE_PROBLEMS as REFERENCE, SHARED_DATA as DATA, need_shared as _need,
                      rigid_motion_2d as _similarity, write_oxford_like_scene as _oxford_like)


def test_make_problem_reproduces_reference_keypoints() -> None:
    ref = load_problem(_need(REFERENCE / "oxford_graf_sift_123.npz"))
    scene = load_scene(_need(DATA), "oxford/graf")
    prob = make_problem(scene, [0, 1, 2], "sift", 500)
    assert prob.name == "oxford_graf_sift_123"
    np.testing.assert_array_equal(prob.view_offsets, ref.view_offsets)
    np.testing.assert_array_equal(prob.keypoints, ref.keypoints)
    np.testing.assert_array_equal(prob.gt_track, ref.gt_track)
    np.testing.assert_array_equal(prob.image_size, ref.image_size)
    np.testing.assert_allclose(prob.scales, ref.scales)
    assert prob.K is None and prob.R is None
    # orientation copies of one location tie on response; the reference broke those ties
    # in an order OpenCV does not expose, so only most orientations agree
    assert np.mean(np.abs(prob.orientations - ref.orientations) < 1e-5) > 0.8


def test_sample_windows_and_names(tmp_path: Path) -> None:
    _oxford_like(tmp_path / "oxford" / "toy", _similarity(0, 2, 1), n=6)
    scene = load_scene(tmp_path, "oxford/toy")
    wins = sample_windows(scene, (3, 4, 6))
    assert wins[:5] == [(0, 1, 2), (1, 2, 3), (2, 3, 4), (3, 4, 5), (0, 1, 2, 3)] and wins[-1] == tuple(range(6))
    assert len(wins) == 8 and sample_windows(scene, (3,), stride=2) == [(0, 1, 2), (2, 3, 4)]
    assert sample_windows(scene, (7,)) == []
    assert problem_name(scene, (0, 1, 2), "orb") == "oxford_toy_orb_123"
    fountain = load_scene(_need(DATA), "strecha/fountain-P11")
    assert problem_name(fountain, (8, 9, 10), "sift") == "strecha_fountain-P11_sift_8-9-10"


def test_convert_end_to_end(tmp_path: Path) -> None:
    _oxford_like(tmp_path / "data" / "oxford" / "toy", _similarity(3, 8, 5), n=3)
    paths = convert(tmp_path / "data", tmp_path / "out", ["oxford/toy"], sizes=(2, 3),
                    detectors=("sift", "orb"), max_features=300, progress=False)
    assert [p.name for p in paths] == [f"oxford_toy_{d}_{w}.npz" for d in ("sift", "orb")
                                       for w in ("12", "23", "123")]
    prob = load_problem(paths[2])
    assert prob.n_views == 3 and prob.K is None and prob.image_size.tolist() == [[240, 180]] * 3
    # a warped copy of one texture: most keypoints come back at their true positions
    assert np.mean(prob.gt_track >= 0) > 0.5
    with pytest.raises(DatasetError, match="no such scene folder"):
        convert(tmp_path / "data", tmp_path / "out", ["oxford/missing"], progress=False)


def test_make_problem_pose_scene() -> None:
    scene = load_scene(_need(DATA), "strecha/fountain-P11")
    prob = make_problem(scene, (4, 5, 6), "sift", 300)
    assert prob.has_poses and prob.K.shape == (3, 3, 3) and prob.descriptors.shape[1] == 128
    np.testing.assert_allclose(prob.R, scene.R[4:7])
    assert (prob.gt_track >= 0).sum() > 30
    with pytest.raises(ValueError, match="distinct"):
        make_problem(scene, (4, 4, 5))
    # photometric labels: same features, other ground truth, more of it labelled
    photo = make_problem(scene, (4, 5, 6), "sift", 300, pose_labels="photometric")
    np.testing.assert_array_equal(photo.keypoints, prob.keypoints)
    assert (photo.gt_track != -2).sum() > (prob.gt_track != -2).sum()
    with pytest.raises(ValueError, match="pose_labels"):
        make_problem(scene, (4, 5, 6), pose_labels="depth")
