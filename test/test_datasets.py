"""Scene readers, features, ground-truth labelling and conversion (gcn_match_ros.datasets)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gcn_match_ros.data.convert import convert, make_problem, problem_name, sample_windows
from gcn_match_ros.data.labels import label_homography, label_poses
from gcn_match_ros.data.scenes import DatasetError, load_scene, read_middlebury, read_oxford, read_strecha
from gcn_match_ros.detect import extract_features
from gcn_match_ros.problem import load_problem

from conftest import look_at

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
DATA = SHARED / "data"
REFERENCE = SHARED / "reference" / "oxford-dev" / "problems"


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"shared data missing: {path}")
    return path


def _texture(width: int = 240, height: int = 180, seed: int = 0) -> np.ndarray:
    """Blurred noise: plenty of SIFT/ORB corners."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (height, width)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _similarity(angle_deg: float, tx: float, ty: float) -> np.ndarray:
    """Rigid 2D motion (distances preserved, so the pixel bands are easy to reason about)."""
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), -np.sin(a), tx], [np.sin(a), np.cos(a), ty], [0, 0, 1]])


def _apply(H: np.ndarray, xy) -> np.ndarray:
    h = np.c_[np.atleast_2d(xy), np.ones(len(np.atleast_2d(xy)))] @ H.T
    return h[:, :2] / h[:, 2:]


# --------------------------------------------------------------------------------------
# Homography labelling
# --------------------------------------------------------------------------------------
def test_homography_labels_synthetic() -> None:
    # views 1, 2 map to view 0 by rigid motions; points are given in view-0 pixels
    to0 = np.stack([np.eye(3), _similarity(0, 30, 20), _similarity(10, -20, 15)])
    from0 = [np.linalg.inv(H) for H in to0]
    sizes = np.array([[400, 300]] * 3)
    rng = np.random.default_rng(1)
    views: list = [[], [], []]
    names: list = [[], [], []]

    def put(v: int, name: str, xy0, offset=(0.0, 0.0)) -> None:
        views[v].append(_apply(from0[v], xy0)[0] + np.asarray(offset))
        names[v].append(name)

    for k, xy in enumerate([(120, 100), (200, 150), (260, 90)]):  # tracks in all views, noisy
        for v in range(3):
            put(v, f"T{k}.{v}", xy, rng.uniform(-0.35, 0.35, 2))
    put(0, "B0", (150, 220))  # B: linked in views 0-1, its view-2 keypoint is 5 px off
    put(1, "B1", (150, 220))
    put(2, "B2", (150, 220), (5.0, 0.0))
    put(0, "C", (320, 250))  # alone: nothing within 10 px anywhere
    put(0, "D0", (80, 240))  # D: 20 px apart -> two unmatched keypoints
    put(1, "D1", (100, 240))
    # a chain p-r-s-q with p, q both in view 0 -> the whole component is unlabelled
    put(0, "p", (300, 180))
    put(0, "q", (304, 180))
    put(1, "r", (301.5, 180))
    put(2, "s", (302.5, 180))
    # u projects just outside image 1 (x = -3): image 1's keypoint at x = 2 does not make u
    # unlabelled, but u (seen from image 1, inside image 0) does make that keypoint unlabelled
    put(0, "u", _apply(to0[1], (-3.0, 60.0))[0])
    put(1, "w", _apply(to0[1], (2.0, 60.0))[0])

    gt = label_homography([np.array(v) for v in views], to0, sizes)
    label = dict(zip(sum(names, []), gt.tolist()))
    tracks = [{label[f"T{k}.{v}"] for v in range(3)} for k in range(3)]
    assert all(len(ids) == 1 and min(ids) >= 0 for ids in tracks)
    assert len(set.union(*tracks)) == 3
    assert label["B0"] == label["B1"] >= 0 and label["B2"] == -2
    assert label["C"] == -1 and label["D0"] == -1 and label["D1"] == -1
    assert label["p"] == label["q"] == label["r"] == label["s"] == -2
    assert label["u"] == -1 and label["w"] == -2


def test_homography_labels_match_reference_problem() -> None:
    path = _need(REFERENCE / "oxford_graf_sift_123.npz")
    ref = load_problem(path)
    scene = read_oxford(_need(DATA / "oxford" / "graf"))
    kps = [ref.keypoints[ref.view_slice(v)] for v in range(ref.n_views)]
    gt = label_homography(kps, scene.homographies[[0, 1, 2]], scene.image_sizes[[0, 1, 2]])
    np.testing.assert_array_equal(gt, ref.gt_track)


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


# --------------------------------------------------------------------------------------
# Pose labelling
# --------------------------------------------------------------------------------------
def _project(K, R, t, X) -> np.ndarray:
    h = (np.atleast_2d(X) @ R.T + t) @ K.T
    return h[:, :2] / h[:, 2:]


def _epipolar_gaps(K, R, t, a: int, b: int, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """(n_a, n_b) larger point-to-epipolar-line distance of every pair (test oracle, built as
    F = [e_b]x P_b P_a^+ rather than from the essential matrix as the module does)."""
    P_a, P_b = K[a] @ np.c_[R[a], t[a]], K[b] @ np.c_[R[b], t[b]]
    e_b = P_b @ np.r_[-R[a].T @ t[a], 1.0]
    F = np.cross(e_b, (P_b @ np.linalg.pinv(P_a)).T).T  # [e_b]x M, column by column
    h_a, h_b = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    l_b, l_a = h_a @ F.T, h_b @ F
    alg = np.abs(l_b @ h_b.T)
    return np.maximum(alg / np.hypot(l_b[:, :1], l_b[:, 1:2]), alg / np.hypot(l_a[:, 0], l_a[:, 1]))


@pytest.fixture(scope="module")
def rig():
    """Three cameras 10 m from the origin, 20 deg apart, and 12 points near the origin."""
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    poses = [look_at(np.array([10 * np.sin(a), -10 * np.cos(a), 0.5]), np.zeros(3))
             for a in np.radians([-20, 0, 20])]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    X = np.random.default_rng(3).uniform(-2, 2, (12, 3))
    return np.stack([K] * 3), R, t, X


def test_pose_labels_synthetic(rig) -> None:
    K, R, t, X = rig
    views = [list(_project(K[v], R[v], t[v], X)) for v in range(3)]
    # Q: seen by all cameras, but its view-2 keypoint is 4 px off -> nothing confirms Q
    Q = np.array([0.5, 0.3, 2.5])
    for v in range(3):
        views[v].append(_project(K[v], R[v], t[v], Q)[0] + (np.array([0.0, 4.0]) if v == 2 else 0))
    # Z lies behind cameras 0 and 1 (its "projections" there are mirrored) and in front of
    # camera 2: it triangulates and reprojects exactly, but is no scene point
    Z = np.array([-5.0, -10.5, 0.5])
    for v in range(3):
        views[v].append(_project(K[v], R[v], t[v], Z)[0])
    # a distractor in view 0, more than 10 px from the epipolar line of every keypoint elsewhere
    grid = np.stack(np.meshgrid(np.arange(5, 640, 15), np.arange(5, 480, 15)), -1).reshape(-1, 2)
    free = np.ones(len(grid), dtype=bool)
    for b in (1, 2):
        free &= (_epipolar_gaps(K, R, t, 0, b, grid, np.array(views[b])) > 12).all(axis=1)
    assert free.any(), "test setup: no free spot for a distractor"
    views[0].append(grid[np.flatnonzero(free)[0]])
    gt = label_poses([np.array(v) for v in views], K, R, t)
    n = len(X)
    per_view = np.split(gt, np.cumsum([len(v) for v in views])[:-1])
    points = np.stack([g[:n] for g in per_view])
    assert np.all(points >= 0) and np.all(points == points[0])  # every point is one track ...
    assert len(np.unique(points[0])) == n  # ... of its own
    assert all(g[n] == -2 for g in per_view)  # Q: epipolar candidates, never confirmed
    assert all(g[n + 1] < 0 for g in per_view)  # Z: fails the cheirality test
    assert per_view[0][n + 2] == -1  # the distractor


@pytest.fixture(scope="module")
def ring():
    """Five cameras 10 m from the origin, 15 deg apart, and 6 points seen by all."""
    K = np.stack([np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])] * 5)
    poses = [look_at(np.array([10 * np.sin(a), -10 * np.cos(a), 0.5]), np.zeros(3))
             for a in np.radians([-30, -15, 0, 15, 30])]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    return K, R, t, np.random.default_rng(4).uniform(-2, 2, (6, 3))


def test_pose_labels_ambiguous_partner_is_unlabelled(ring) -> None:
    # Y hides behind X on camera 4's ray, so camera 4's keypoint of X has two confirmed
    # partners in views 2 and 3 (X's and Y's)
    K, R, t, P = ring
    X = np.vstack([P, [0.3, -0.4, 0.2]])
    C4 = -R[4].T @ t[4]
    Y = C4 + 0.8 * (X[-1] - C4)
    views = [_project(K[v], R[v], t[v], X) for v in range(5)]
    views[2] = np.vstack([views[2], _project(K[2], R[2], t[2], Y)])
    views[3] = np.vstack([views[3], _project(K[3], R[3], t[3], Y)])
    gt = label_poses(views, K, R, t)
    per_view = np.split(gt, np.cumsum([len(v) for v in views])[:-1])
    ordinary = np.stack([g[:6] for g in per_view])
    assert np.all(ordinary >= 0) and np.all(ordinary == ordinary[0])
    assert per_view[4][6] == -2  # the keypoint with two partners per view ...
    assert np.all(per_view[2][6:] == -2) and np.all(per_view[3][6:] == -2)  # ... and those partners
    # uniqueness drops only the ambiguous links: X keeps its track in views 0 and 1
    assert per_view[0][6] == per_view[1][6] >= 0 and per_view[0][6] not in ordinary[0]


def test_pose_labels_chain_that_does_not_close(ring) -> None:
    # X (views 0-2) and Y (views 2-4) share camera 2's keypoint: every link is unique and
    # confirmed, but X's and Y's keypoints are not epipolar-consistent -> no track
    K, R, t, P = ring
    X = np.array([0.3, -0.4, 0.2])
    C2 = -R[2].T @ t[2]
    Y = C2 + 0.8 * (X - C2)
    views = [np.vstack([_project(K[v], R[v], t[v], P), _project(K[v], R[v], t[v], X if v < 3 else Y)])
             for v in range(5)]
    gt = label_poses(views, K, R, t).reshape(5, 7)
    assert np.all(gt[:, :6] >= 0) and np.all(gt[:, :6] == gt[0, :6])
    assert np.all(gt[:, 6] == -2)


def test_pose_labels_need_three_views(rig) -> None:
    K, R, t, X = rig
    with pytest.raises(ValueError, match="at least 3 views"):
        label_poses([_project(K[v], R[v], t[v], X) for v in range(2)], K[:2], R[:2], t[:2])


# --------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------
def _oxford_like(folder: Path, H: np.ndarray, n: int = 2) -> None:
    folder.mkdir(parents=True)
    img = _texture()
    for v in range(1, n + 1):
        warped = cv2.warpPerspective(img, np.linalg.matrix_power(H, v - 1), img.shape[::-1])
        cv2.imwrite(str(folder / f"img{v}.png"), warped)
        if v > 1:
            np.savetxt(folder / f"H1to{v}p", np.linalg.matrix_power(H, v - 1))


def test_read_oxford(tmp_path: Path) -> None:
    H = _similarity(0, 6, 4)
    _oxford_like(tmp_path / "oxford" / "toy", H, n=3)
    scene = read_oxford(tmp_path / "oxford" / "toy")
    assert scene.name == "oxford_toy" and scene.kind == "homography" and scene.n_views == 3
    assert scene.view_labels == ("1", "2", "3")
    np.testing.assert_array_equal(scene.image_sizes, [[240, 180]] * 3)
    np.testing.assert_allclose(scene.homographies[2], np.linalg.inv(H @ H))


@pytest.mark.parametrize("content, message", [
    ("1 0 0\n0 1 0\n0 0", "expected 9"),
    ("1 0 0\n0 1 x\n0 0 1", "expected 9"),
    ("1 0 0\n1 0 0\n0 0 1", "singular"),
])
def test_read_oxford_rejects_bad_homography(tmp_path: Path, content: str, message: str) -> None:
    _oxford_like(tmp_path / "toy", _similarity(0, 6, 4))
    (tmp_path / "toy" / "H1to2p").write_text(content)
    with pytest.raises(DatasetError, match=message) as err:
        read_oxford(tmp_path / "toy")
    assert "H1to2p" in str(err.value)


def test_read_oxford_missing_homography(tmp_path: Path) -> None:
    _oxford_like(tmp_path / "toy", _similarity(0, 6, 4))
    (tmp_path / "toy" / "H1to2p").unlink()
    with pytest.raises(DatasetError, match="H1to2p"):
        read_oxford(tmp_path / "toy")


def _strecha_like(folder: Path, n: int = 3) -> None:
    folder.mkdir(parents=True)
    for v in range(n):
        cv2.imwrite(str(folder / f"{v:04d}.png"), _texture(seed=v))
        R, t = look_at(np.array([v, -10.0, 0.0]), np.zeros(3))
        (folder / f"{v:04d}.cam").write_text(
            "# toy\nK 500 0 120 0 500 90 0 0 1\n"
            f"R {' '.join(map(str, R.ravel()))}\nt {' '.join(map(str, t))}\n")


def test_read_strecha(tmp_path: Path) -> None:
    _strecha_like(tmp_path / "strecha" / "toy")
    scene = load_scene(tmp_path, "strecha/toy")
    assert scene.name == "strecha_toy" and scene.kind == "poses" and scene.n_views == 3
    assert scene.K.shape == (3, 3, 3) and scene.t.shape == (3, 3)
    C = -np.einsum("vji,vj->vi", scene.R, scene.t)
    np.testing.assert_allclose(C[2], [2, -10, 0], atol=1e-9)


@pytest.mark.parametrize("bad, message", [
    ("K 500 0 120 0 500 90 0 0", "K: expected 9"),
    ("R 1 0 0 0 1 0 0 0 2", "not a rotation"),
    ("t 1 2", "t: expected 3"),
    ("Q 1 2 3", "unexpected line"),
])
def test_read_strecha_rejects_bad_cam(tmp_path: Path, bad: str, message: str) -> None:
    _strecha_like(tmp_path / "toy")
    cam = tmp_path / "toy" / "0001.cam"
    lines = cam.read_text().splitlines()
    key = bad.split()[0]
    lines = [bad if ln.startswith(key + " ") else ln for ln in lines] + ([bad] if key == "Q" else [])
    cam.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=message) as err:
        read_strecha(tmp_path / "toy")
    assert "0001.cam" in str(err.value)


def test_read_strecha_missing_line(tmp_path: Path) -> None:
    _strecha_like(tmp_path / "toy")
    cam = tmp_path / "toy" / "0002.cam"
    cam.write_text("\n".join(ln for ln in cam.read_text().splitlines() if not ln.startswith("t ")))
    with pytest.raises(DatasetError, match=r"0002\.cam: missing line\(s\) t"):
        read_strecha(tmp_path / "toy")


def test_read_middlebury_rejects_bad_par(tmp_path: Path) -> None:
    folder = tmp_path / "middlebury_toy"
    folder.mkdir()
    row = "1500 0 300 0 1500 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1"
    for v in (1, 2):
        cv2.imwrite(str(folder / f"toy{v:04d}.png"), _texture(seed=v))
    par = folder / "templeSR_par.txt"
    par.write_text(f"2\ntoy0001.png {row}\ntoy0002.png {row}\n")
    assert read_middlebury(folder).view_labels == ("1", "2")
    par.write_text(f"3\ntoy0001.png {row}\ntoy0002.png {row}\n")
    with pytest.raises(DatasetError, match="templeSR_par.txt: header says 3"):
        read_middlebury(folder)
    par.write_text(f"2\ntoy0001.png {row}\ntoy0002.png {row[:-2]}\n")
    with pytest.raises(DatasetError, match="templeSR_par.txt: image toy0002.png: expected 21"):
        read_middlebury(folder)


def test_load_scene_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such scene folder"):
        load_scene(tmp_path, "oxford/nowhere")
    with pytest.raises(DatasetError, match="unknown dataset"):
        load_scene(tmp_path, "kitti/00")


def test_real_readers() -> None:
    fountain = load_scene(_need(DATA), "strecha/fountain-P11")
    assert fountain.n_views == 11 and fountain.image_sizes.tolist() == [[768, 512]] * 11
    temple = load_scene(DATA, "middlebury_temple")
    assert temple.n_views == 6 and temple.view_labels[0] == "6"


# --------------------------------------------------------------------------------------
# Features, windows, conversion
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("detector, dim", [("sift", 128), ("orb", 256)])
def test_extract_features(detector: str, dim: int) -> None:
    img = _texture(320, 240)
    f = extract_features(img, detector, 300)
    assert 50 < len(f.keypoints) <= 300 and f.descriptors.shape == (len(f.keypoints), dim)
    assert f.keypoints.dtype == f.descriptors.dtype == f.scales.dtype == f.orientations.dtype == np.float32
    if detector == "orb":
        assert set(np.unique(f.descriptors)) <= {0.0, 1.0}
    assert np.all((f.orientations >= 0) & (f.orientations < 2 * np.pi + 1e-6))
    d = np.linalg.norm(f.keypoints[:, None] - f.keypoints[None], axis=-1) + np.eye(len(f.keypoints)) * 99
    assert d.min() > 1.5  # one keypoint per location
    g = extract_features(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), detector, 300)
    np.testing.assert_array_equal(f.keypoints, g.keypoints)  # colour is converted; deterministic
    np.testing.assert_array_equal(f.descriptors, g.descriptors)


def test_extract_features_rejects_unknown_detector() -> None:
    with pytest.raises(ValueError, match="detector"):
        extract_features(_texture(), "surf")


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
