"""Tests of gcn_match_ros.problem: Problem and Result, their .npz files and validation."""
import numpy as np
import pytest

from gcn_match_ros.problem import (MAX_ABS_DESCRIPTOR, MAX_ABS_PIXEL, FormatError, Problem, Result,
                                   descriptor_range_fault, intrinsics_fault, keypoint_range_fault, load_problem,
                                   rotation_fault,
                                   load_result, save_problem, save_result)

from conftest import permuted_views_problem, posed_problem, reference_problem_path


def _arrays(problem: Problem) -> dict:
    return {k: getattr(problem, k) for k in ("view_offsets", "keypoints", "descriptors", "gt_track")}


def test_round_trip(tmp_path):
    p = permuted_views_problem()
    p.K = np.tile(np.eye(3), (3, 1, 1))
    save_problem(p, tmp_path / "p.npz")
    q = load_problem(tmp_path / "p.npz")
    for key in ("view_offsets", "keypoints", "descriptors", "gt_track", "K"):
        np.testing.assert_array_equal(getattr(p, key), getattr(q, key))
    assert q.descriptors.dtype == np.float32 and q.view_offsets.dtype == np.int64 and q.K.dtype == np.float64
    assert q.name == "p"


def test_reference_problem_loads():
    p = load_problem(reference_problem_path())
    assert p.n_views == 3 and p.gt_track is not None and p.n_keypoints == p.view_offsets[-1]


@pytest.mark.parametrize("change, key", [
    (lambda a: a.pop("descriptors"), "descriptors"),
    (lambda a: a.update(keypoints=np.zeros((5, 3), np.float32)), "keypoints"),
    (lambda a: a.update(view_offsets=np.array([0, 5, 4])), "view_offsets"),
    (lambda a: a.update(gt_track=np.zeros(7, np.int64)), "gt_track"),
    (lambda a: a.update(gt_track=np.full(36, -3)), "gt_track"),
    (lambda a: a.update(descriptors=np.full((36, 16), np.nan, np.float32)), "descriptors"),
    (lambda a: a.update(keypoints=np.array(["x"] * 72).reshape(36, 2)), "keypoints"),
    (lambda a: a.update(K=np.zeros((2, 3, 3))), "K"),
    # finite but meaningless: a similarity overflowing to NaN, an essential matrix's threshold px / 0
    (lambda a: a["keypoints"].__setitem__(7, 1e30), "keypoints"),
    (lambda a: a["descriptors"].__setitem__((3, 0), 2 * MAX_ABS_DESCRIPTOR), "descriptors"),
    (lambda a: a.update(K=np.tile(np.diag([-500.0, 500.0, 1.0]), (3, 1, 1))), "K"),
])
def test_malformed_files_name_the_key(tmp_path, change, key):
    arrays = _arrays(permuted_views_problem())
    change(arrays)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError, match=f"'{key}'"):
        load_problem(tmp_path / "bad.npz")


def test_pickled_and_garbage_files_are_refused(tmp_path):
    np.savez(tmp_path / "obj.npz", view_offsets=np.array([0, 1], dtype=object),
             keypoints=np.zeros((1, 2)), descriptors=np.zeros((1, 2)))
    with pytest.raises(FormatError):
        load_problem(tmp_path / "obj.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="not a readable"):
        load_problem(tmp_path / "junk.npz")
    with pytest.raises(FormatError, match="no such file"):
        load_problem(tmp_path / "missing.npz")


def test_result_round_trip_and_validation(tmp_path):
    p = permuted_views_problem(n_views=2, n_points=3)
    r = Result(track=[0, 1, -1, 0, 1, -1], pair_rows=[0, 1], pair_cols=[3, 4], pair_scores=[0.9, 0.8],
               seconds=0.5, method="x:y=1")
    r.validate_against(p)
    save_result(r, tmp_path / "r.npz")
    q = load_result(tmp_path / "r.npz")
    assert q.method == "x:y=1" and q.seconds == 0.5
    np.testing.assert_array_equal(q.track, r.track)
    with pytest.raises(FormatError, match="pair_rows"):
        Result(track=[0], pair_rows=[3], pair_cols=[1], pair_scores=[0.1])
    bad = Result(track=[0, 0, -1, -1, -1, -1], pair_rows=[], pair_cols=[], pair_scores=[])
    with pytest.raises(FormatError, match="cycle-consistent"):
        bad.validate_against(p)
    same_view = Result(track=[-1] * 6, pair_rows=[0], pair_cols=[1], pair_scores=[0.5])
    with pytest.raises(FormatError, match="different views"):
        same_view.validate_against(p)


def test_subset_views():
    p = permuted_views_problem(n_views=4, n_points=5)
    q = p.subset_views([2, 0])
    assert q.n_views == 2 and q.n_keypoints == 10
    np.testing.assert_array_equal(q.descriptors[:5], p.descriptors[10:15])


def test_atomic_write_gives_the_usual_file_mode(tmp_path):
    import os
    from gcn_match_ros.problem import atomic_write

    target = tmp_path / "out.bin"
    atomic_write(target, lambda p: open(p, "wb").write(b"x"))
    plain = tmp_path / "plain.bin"
    plain.write_bytes(b"x")
    assert target.read_bytes() == b"x"
    assert os.stat(target).st_mode & 0o777 == os.stat(plain).st_mode & 0o777
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_camera_ids_name_every_view_and_follow_subsets():
    import pytest as _pytest

    from gcn_match_ros.problem import FormatError, Problem

    kw = dict(view_offsets=[0, 2, 3], keypoints=np.zeros((3, 2)), descriptors=np.ones((3, 4)))
    p = Problem(camera_ids=["cam0", "cam1"], **kw)
    assert p.camera_ids == ("cam0", "cam1")
    assert p.subset_views([1]).camera_ids == ("cam1",) and Problem(**kw).subset_views([1]).camera_ids is None
    with _pytest.raises(FormatError, match="camera_ids"):
        Problem(camera_ids=["cam0"], **kw)


def test_range_faults_name_what_no_camera_or_detector_produces():
    kp = np.array([[0.0, 0.0], [639.5, 479.0], [-0.5, 480.9]])
    assert keypoint_range_fault(kp) is None and keypoint_range_fault(kp, np.array([640, 480])) is None
    assert keypoint_range_fault(np.zeros((0, 2)), np.array([640, 480])) is None
    assert "2 keypoints outside their image (e.g. #1 at [700.0, 0.0] in a 640 x 480 image)" == \
        keypoint_range_fault(np.array([[1.0, 1.0], [700.0, 0.0], [3.0, -2.0]]), np.array([640, 480]))
    # an image size that is not positive is unknown: only the magnitude is checked
    unknown = np.array([0, 0])
    assert keypoint_range_fault(np.array([[600.0, 400.0], [5000.0, 1.0]]), unknown) is None
    assert "more than 1e+05" in keypoint_range_fault(np.array([[600.0, 400.0], [2 * MAX_ABS_PIXEL, 1.0]]), unknown)
    assert descriptor_range_fault(np.full((2, 4), 255.0)) is None and descriptor_range_fault(np.zeros((0, 4))) is None
    assert descriptor_range_fault(np.array([[0.0, -3e6]])) == "descriptor values up to 3e+06 (more than 1e+06)"


def test_intrinsics_fault_knows_a_pinhole_matrix():
    K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
    assert intrinsics_fault(K) is None and intrinsics_fault(np.stack([K, np.eye(3)])) is None
    assert intrinsics_fault(np.diag([-500.0, 500.0, 1.0])) == "focal lengths fx = -500, fy = 500: both must be positive"
    assert intrinsics_fault(np.stack([K, np.diag([500.0, 0.0, 1.0])])).endswith("(view 1): both must be positive")
    assert intrinsics_fault(K * 2).startswith("last row [0.0, 0.0, 2.0]")
    assert intrinsics_fault(np.full((3, 3), np.inf)) == "not finite"


def test_rotation_fault_knows_a_rotation():
    c, s_ = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    assert rotation_fault(R) is None and rotation_fault(np.stack([R, np.eye(3)])) is None
    assert rotation_fault(R + 1e-6) is None  # a stored rotation's rounding
    assert rotation_fault(2 * R).startswith("not a rotation: |R Rᵀ - I| up to 3")
    reflection = np.diag([1.0, 1.0, -1.0])
    assert rotation_fault(np.stack([R, reflection])).startswith("not a rotation (view 1)")
    posed = posed_problem(np.random.default_rng(0))
    with pytest.raises(FormatError, match="'R': not a rotation"):
        Problem(view_offsets=posed.view_offsets, keypoints=posed.keypoints, descriptors=posed.descriptors,
                K=posed.K, R=posed.R * 1.01, t=posed.t)
