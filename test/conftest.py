"""Shared fixtures and helpers: paths to ../shared, small random problems, camera frames,
bags, scenes and tiny models that several test files use.

ROS tests talk DDS on this machine only: discovery is confined to it here, before any test
module imports rclpy (``./run.sh test`` sets the same).
"""
from __future__ import annotations

import itertools
import os
import random
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # no traffic leaves the machine
os.environ.pop("ROS_LOCALHOST_ONLY", None)
# ROS logs of the test nodes go to a directory of this run, removed when it ends (one given in
# ROS_LOG_DIR is the caller's and stays)
_OWN_LOG_DIR = None
if not os.environ.get("ROS_LOG_DIR"):
    _OWN_LOG_DIR = os.environ["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix="gcn_match_ros-test-roslog-")


def pytest_sessionfinish(session, exitstatus):
    if _OWN_LOG_DIR is not None:
        shutil.rmtree(_OWN_LOG_DIR, ignore_errors=True)

from gcn_match_ros.data import synthetic  # noqa: E402
from gcn_match_ros.graph import CorrespondenceGraph, GraphConfig, build_graph  # noqa: E402
from gcn_match_ros.learn.model import GCNConfig, graph_tensors  # noqa: E402
from gcn_match_ros.node_features import feature_dim, node_features  # noqa: E402
from gcn_match_ros.problem import Problem  # noqa: E402
from gcn_match_ros.stamps import seconds_to_ns  # noqa: E402
from gcn_match_ros.windowing import Frame  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SHARED_DATA = SHARED / "data"
REFERENCE_PROBLEMS = SHARED / "reference" / "oxford-dev" / "problems"
SAMPLE_BAGS = REPO / "bags"


#: the CPUs this process may use, in order (empty where threads cannot be placed on CPUs)
PROCESS_CPUS = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
#: for tests that pin the solve's two threads (threads.pinned_solve_threads, cpu_affinity)
needs_two_cpus = pytest.mark.skipif(len(PROCESS_CPUS) < 2, reason="needs Linux and two CPUs this process may use")


def second_thread_cpus() -> set:
    """The CPUs the process's second thread (threads.alongside) may run on now, asked on that thread."""
    from gcn_match_ros.threads import _second_thread
    return _second_thread().submit(os.sched_getaffinity, 0).result()


def permuted_views_problem(n_views: int = 3, n_points: int = 12, dim: int = 16, noise: float = 0.0,
                           seed: int = 0) -> Problem:
    """V views of the same p points in random order; descriptors = point descriptor + noise."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(n_points, dim))
    kps, desc, gt = [], [], []
    for _ in range(n_views):
        perm = rng.permutation(n_points)
        desc.append(base[perm] + noise * rng.normal(size=(n_points, dim)))
        kps.append(rng.uniform(0, 100, size=(n_points, 2)))
        gt.append(perm)
    offsets = np.arange(n_views + 1) * n_points
    return Problem(view_offsets=offsets, keypoints=np.concatenate(kps), descriptors=np.concatenate(desc),
                   gt_track=np.concatenate(gt), name="permuted")


def look_at(centre: np.ndarray, target: np.ndarray, down=(0.0, 0.0, -1.0)) -> tuple:
    """World->camera R, t for a camera at ``centre`` looking at ``target`` (y down, along the
    world's ``down``: -z by default)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(np.asarray(down, np.float64), z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


def random_rotation(rng) -> np.ndarray:
    """A random rotation matrix (QR of a Gaussian matrix, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run a module's torch ops on one intra-op thread, restoring the count afterwards."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def small_problem() -> Problem:
    return permuted_views_problem()


def reference_problem_path(name: str = "oxford_graf_sift_123") -> Path:
    path = REFERENCE_PROBLEMS / f"{name}.npz"
    if not path.is_file():
        pytest.fail(f"shared reference data missing: {path} (the repository must sit beside shared/)")
    return path


def need_shared(path: Path) -> Path:
    """``path`` of ../shared; a test that needs it fails when it is missing (the repository must
    sit beside shared/), it is never skipped."""
    if not path.exists():
        pytest.fail(f"shared data missing: {path} (the repository must sit beside shared/)")
    return path


def domain_id() -> int:
    """A random ROS domain for one test's DDS traffic."""
    return random.SystemRandom().randint(1, 100)


class PermutedScene:
    """Descriptors of ``points`` scene points; every camera sees all of them permuted, with
    noise, plus a few distractors (gt -1). Keypoint positions are per point + 0.5 px noise (a
    detector's localisation error: matches are verified against two-view geometry)."""

    def __init__(self, points: int = 60, dim: int = 128, noise: float = 0.05, distractors: int = 5,
                 seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.base = np.abs(self.rng.normal(size=(points, dim)))
        self.xy = self.rng.uniform((20, 20), (620, 460), size=(points, 2))  # inside the 640 x 480 image
        self.points, self.dim, self.noise, self.distractors = points, dim, noise, distractors

    def frame(self, cam: str, seconds: float):
        """(Frame stamped ``seconds``, its (N,) ground truth)."""
        rng, p = self.rng, self.points
        perm = rng.permutation(p)
        desc = np.abs(self.base[perm] + self.noise * rng.normal(size=(p, self.dim)))
        xy = self.xy[perm] + rng.normal(scale=0.5, size=(p, 2))
        if self.distractors:
            desc = np.vstack([desc, np.abs(rng.normal(size=(self.distractors, self.dim)))])
            xy = np.vstack([xy, rng.uniform((20, 20), (620, 460), size=(self.distractors, 2))])
        gt = np.concatenate([perm, -np.ones(self.distractors, np.int64)])
        f = Frame(camera_id=cam, stamp_ns=seconds_to_ns(seconds), keypoints=xy.astype(np.float32),
                  descriptors=desc.astype(np.float32), frame_id=f"{cam}_optical_frame",
                  scales=np.full(len(gt), 3.0, np.float32), orientations=np.zeros(len(gt), np.float32),
                  K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), image_size=(640, 480),
                  descriptor_name="sift")
        return f, gt


# --------------------------------------------------------------------------------------
# Camera frames as bags hold them (test_bags_*, test_ros_bag_tools)
# --------------------------------------------------------------------------------------
BAG_CAMERAS = ("cam0", "cam1", "cam2")


def synthetic_frames(steps: int = 5, dim: int = 8, seed: int = 0, skip=((3, "cam2"),)):
    """BAG_CAMERAS x steps frames (camera j stamped 2 ms after camera 0), random sizes, scores,
    poses and K on cam0/cam1 (cam2 uncalibrated, no pose); scene-global labels."""
    rng = np.random.default_rng(seed)
    frames = {c: [] for c in BAG_CAMERAS}
    labels = {c: [] for c in BAG_CAMERAS}
    for k in range(steps):
        for j, cam in enumerate(BAG_CAMERAS):
            if (k, cam) in skip:
                continue
            n = int(rng.integers(5, 40))
            calibrated = cam != "cam2"
            K = np.array([[500.0 + j, 0, 320], [0, 501.0, 240], [0, 0, 1]]) if calibrated else None
            frames[cam].append(Frame(
                camera_id=cam, stamp_ns=1_700_000_000 * 10**9 + k * 10**8 + j * 2 * 10**6,
                keypoints=rng.uniform((0, 0), (600, 450), (n, 2)).astype(np.float32),  # inside 640 x 480
                descriptors=rng.normal(size=(n, dim)).astype(np.float32), frame_id=f"{cam}_optical_frame",
                scales=rng.uniform(1, 9, n).astype(np.float32),
                orientations=rng.uniform(-3, 3, n).astype(np.float32),
                scores=rng.uniform(0, 1, n).astype(np.float32), K=K,
                image_size=(640, 480) if calibrated else None,
                R=random_rotation(rng) if calibrated else None, t=rng.normal(size=3) if calibrated else None))
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


# --------------------------------------------------------------------------------------
# Training bags from generated scenes (test_bags_source, test_cli)
# --------------------------------------------------------------------------------------
TINY_BAG_SCENE = synthetic.rome16k(3, n_points=14, descriptor_dim=16, descriptor_noise=1.0)


def scene_problems(seed, count, two_view_at=()):
    out = []
    for k in range(count):
        p = synthetic.random_scene_problem(TINY_BAG_SCENE, np.random.default_rng([seed, k]), name=f"s{seed}_{k}")
        out.append(p.subset_views([0, 1]) if k in two_view_at else p)
    return out


@pytest.fixture(scope="module")
def tiny_bags(tmp_path_factory):
    """(training bag of scene_a: 6 windows, one of them 2 views; validation bag of scene_b:
    3 windows; the training bag's problems)."""
    from gcn_match_ros.bags.make import write_problems_bag

    d = tmp_path_factory.mktemp("bags")
    probs = scene_problems(1, 6, two_view_at=(3,))
    train_bag = write_problems_bag(d / "scene_a.mcap", probs)
    val_bag = write_problems_bag(d / "scene_b.mcap", scene_problems(2, 3))
    return train_bag, val_bag, probs


# --------------------------------------------------------------------------------------
# Posed problems and a tiny GCN for them (test_learn_objective, _sources, _train, _checkpoint)
# --------------------------------------------------------------------------------------
POSED_DESCRIPTOR_DIM = 8
POSED_GCN = GCNConfig(in_dim=feature_dim(POSED_DESCRIPTOR_DIM), widths=(16, 16, 16, 16), out_dim=16, groups=4,
                      skip_layers=(2, 4))


def posed_problem(rng, n_views=3, p=8, noise=0.3):
    """p scene points seen by every view in random order; descriptors = point descriptor + noise."""
    D = POSED_DESCRIPTOR_DIM
    K = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    P = rng.uniform(-1, 1, size=(p, 3))
    base = rng.normal(size=(p, D))
    kps, desc, gt, Rs, ts = [], [], [], [], []
    for _ in range(n_views):
        R, t = random_rotation(rng), np.array([0.0, 0.0, 5.0]) + 0.3 * rng.normal(size=3)
        perm = rng.permutation(p)
        x = (K @ (R @ P[perm].T + t[:, None])).T
        kps.append(x[:, :2] / x[:, 2:])
        desc.append(base[perm] + noise * rng.normal(size=(p, D)))
        gt.append(perm)
        Rs.append(R)
        ts.append(t)
    return Problem(view_offsets=np.arange(n_views + 1) * p, keypoints=np.concatenate(kps),
                   descriptors=np.concatenate(desc), K=np.stack([K] * n_views), R=np.stack(Rs),
                   t=np.stack(ts), image_size=np.tile([640, 480], (n_views, 1)), gt_track=np.concatenate(gt))


def failing_torch_save(monkeypatch, should_fail):
    """Make checkpoint writes whose file name ``should_fail`` leave a partial file and raise."""
    import torch

    from gcn_match_ros.learn import checkpoint as checkpoint_mod

    real = torch.save

    def fake(obj, f, *args, **kwargs):
        if should_fail(os.path.basename(f)):
            with open(f, "wb") as fh:
                fh.write(b"partial")  # a half-written file ...
            raise OSError("disk full")  # ... then the write fails
        return real(obj, f, *args, **kwargs)

    monkeypatch.setattr(checkpoint_mod.torch, "save", fake)


# --------------------------------------------------------------------------------------
# Permuted problems with keypoint attributes and a small GCN (test_learn_model, _checkpoint)
# --------------------------------------------------------------------------------------
SMALL_GCN_LAYERS = dict(widths=(16, 16, 24, 24), out_dim=12, groups=4, skip_layers=(2, 4))


def permuted_views_problem_with_attributes(n_views=3, p=20, dim=16, noise=0.3, seed=0):
    """V views of the same p points, each view a random permutation with noisy descriptors;
    keypoints with scales, orientations and image sizes (every node feature)."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(p, dim))
    desc, kps, gt = [], [], []
    for _ in range(n_views):
        perm = rng.permutation(p)
        desc.append(base[perm] + noise * rng.normal(size=(p, dim)))
        kps.append(rng.uniform(0, 640, size=(p, 2)))
        gt.append(perm)
    return Problem(view_offsets=np.arange(n_views + 1) * p, keypoints=np.concatenate(kps),
                   descriptors=np.concatenate(desc), scales=rng.uniform(1, 10, n_views * p),
                   orientations=rng.uniform(-np.pi, np.pi, n_views * p),
                   image_size=np.tile([640, 480], (n_views, 1)), gt_track=np.concatenate(gt))


def gcn_inputs(problem, graph_config=GraphConfig()):
    """(node features, edge_index, edge_weight, graph) of ``problem`` for the GCN."""
    import torch

    g = build_graph(problem, graph_config)
    ei, ew = graph_tensors(g)
    return torch.from_numpy(node_features(problem)), ei, ew, g


# --------------------------------------------------------------------------------------
# Calibrated scenes for epipolar geometry (test_geometry, test_learn_losses)
# --------------------------------------------------------------------------------------
def calibrated_scene(rng, n_views=3, p=12, K=np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])):
    """Points near the origin seen by cameras ~5 units away; every view a permutation."""
    P = rng.uniform(-1, 1, size=(p, 3))
    Rs, ts, kps, tracks = [], [], [], []
    for _ in range(n_views):
        R = random_rotation(rng)
        t = np.array([0.0, 0.0, 5.0]) + 0.3 * rng.normal(size=3)
        perm = rng.permutation(p)
        x = (K @ (R @ P[perm].T + t[:, None])).T
        kps.append(x[:, :2] / x[:, 2:])
        Rs.append(R)
        ts.append(t)
        tracks.append(perm)
    prob = Problem(view_offsets=np.arange(n_views + 1) * p, keypoints=np.concatenate(kps).astype(np.float32),
                   descriptors=np.ones((n_views * p, 4), np.float32), K=np.stack([K] * n_views),
                   R=np.stack(Rs), t=np.stack(ts), gt_track=np.concatenate(tracks))
    # exact calibrated points (float32 keypoints would add ~1e-7 noise)
    X = np.concatenate([(R @ P[perm].T + t[:, None]).T for R, t, perm in zip(Rs, ts, tracks)])
    X = X / X[:, 2:]
    return prob, X


# --------------------------------------------------------------------------------------
# Scene folders and images (test_data_*, test_detect)
# --------------------------------------------------------------------------------------
def blurred_noise_image(width: int = 240, height: int = 180, seed: int = 0) -> np.ndarray:
    """Blurred noise: plenty of SIFT/ORB corners."""
    import cv2

    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (height, width)).astype(np.float32), (0, 0), 2.0)
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def rigid_motion_2d(angle_deg: float, tx: float, ty: float) -> np.ndarray:
    """Rigid 2D motion (distances preserved, so the pixel bands are easy to reason about)."""
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), -np.sin(a), tx], [np.sin(a), np.cos(a), ty], [0, 0, 1]])


def write_oxford_like_scene(folder: Path, H: np.ndarray, n: int = 2) -> None:
    """An Oxford-layout scene: img1..img<n>.png, image v warped by H^(v-1), and H1to<v>p files."""
    import cv2

    folder.mkdir(parents=True)
    img = blurred_noise_image()
    for v in range(1, n + 1):
        warped = cv2.warpPerspective(img, np.linalg.matrix_power(H, v - 1), img.shape[::-1])
        cv2.imwrite(str(folder / f"img{v}.png"), warped)
        if v > 1:
            np.savetxt(folder / f"H1to{v}p", np.linalg.matrix_power(H, v - 1))


# --------------------------------------------------------------------------------------
# A textured plane seen by four posed cameras (test_data_plane_sweep, test_data_labels)
# --------------------------------------------------------------------------------------
PLANE_IMAGE_SIZE = (640, 480)
PLANE_TEXTURE_M_PER_PX = 0.01


@pytest.fixture(scope="module")
def plane_views():
    """Four cameras 10 m from a textured plane (world y = 0), 8 deg apart, and their images."""
    import cv2

    rng = np.random.default_rng(0)
    h, w = 1000, 1200
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 3.0)
    texture = cv2.normalize(texture, None, 0, 255, cv2.NORM_MINMAX)
    s = PLANE_TEXTURE_M_PER_PX
    # texture pixel (u, v) -> world (X, 0, Z), texture centre at the origin, v down = Z down
    S = np.array([[s, 0, -s * w / 2], [0, 0, 0], [0, -s, s * h / 2]])
    K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
    poses = [look_at(np.array([10 * np.sin(a), -10 * np.cos(a), 0.3]), np.zeros(3))
             for a in np.radians([-12, -4, 4, 12])]
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    images = [cv2.warpPerspective(texture, K @ (Rv @ S + np.outer(tv, [0, 0, 1])), PLANE_IMAGE_SIZE,
                                  flags=cv2.INTER_LINEAR)
              for Rv, tv in zip(R, t)]
    return np.stack([K] * 4), R, t, [im.astype(np.float32) for im in images]


def plane_points(n: int, seed: int) -> np.ndarray:
    """n random points on the textured plane (world y = 0)."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-2.5, 2.5, n), np.zeros(n), rng.uniform(-1.8, 1.8, n)]


# --------------------------------------------------------------------------------------
# Generated problems compared field by field (test_data_synthetic, _permutation_noise)
# --------------------------------------------------------------------------------------
PROBLEM_KEYS = ("view_offsets", "keypoints", "descriptors", "scales", "orientations", "K", "R", "t",
                "image_size", "gt_track")


def same_problem(a: Problem, b: Problem) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in PROBLEM_KEYS)


def same_track_pairs(gt, view):
    """[(i, j), ...], i < j, keypoints in different views with the same gt >= 0, track by track."""
    out = []
    for g in np.unique(gt[gt >= 0]):
        idx = np.flatnonzero(gt == g)
        out += [(int(a), int(b)) for a, b in itertools.combinations(idx, 2) if view[a] != view[b]]
    return out


def true_pair_set(gt, view):
    """Set of (i, j), i < j, keypoints in different views with the same gt >= 0."""
    return set(same_track_pairs(gt, view))


# --------------------------------------------------------------------------------------
# Problems with a known answer and graphs of chosen pairs (test_solvers, test_rounding)
# --------------------------------------------------------------------------------------
def known_answer_problem(n_views: int, n_points: int, visibility: float = 1.0, seed: int = 0,
                         dim: int = 16) -> Problem:
    """Each view sees a random subset (all when visibility = 1) of p points in random order.

    Descriptors are the point's descriptor, identical in every view (noiseless); gt_track is the
    point id, -1 for a point seen by a single view.
    """
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(n_points, dim))
    seen = rng.random((n_views, n_points)) < visibility
    seen[rng.integers(n_views, size=n_points), np.arange(n_points)] = True  # every point somewhere
    ids = [rng.permutation(np.flatnonzero(seen[v])) for v in range(n_views)]
    gt = np.concatenate(ids)
    n_seen = seen.sum(axis=0)
    gt = np.where(n_seen[gt] >= 2, gt, -1)
    offsets = np.r_[0, np.cumsum([len(i) for i in ids])]
    return Problem(view_offsets=offsets, keypoints=rng.uniform(0, 100, size=(len(gt), 2)),
                   descriptors=base[np.concatenate(ids)], gt_track=gt, name=f"perm{n_views}x{n_points}")


def true_pair_list(problem: Problem):
    """[(a, b), ...] keypoints of different views on the same ground-truth track, a < b."""
    return same_track_pairs(problem.gt_track, problem.view_index)


def graph_from_pairs(problem: Problem, pairs) -> CorrespondenceGraph:
    """Binary graph with exactly these undirected pairs (stored both ways, sorted)."""
    pairs = np.asarray(sorted(set((min(a, b), max(a, b)) for a, b in pairs)), np.int64).reshape(-1, 2)
    rows = np.r_[pairs[:, 0], pairs[:, 1]]
    cols = np.r_[pairs[:, 1], pairs[:, 0]]
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    e = rows.size
    return CorrespondenceGraph(problem.view_offsets.copy(), rows, cols, np.ones(e, np.float32),
                               np.ones(e, np.float32), np.zeros(e, np.float32), np.zeros(e, np.int64))


def corrupted_pairs(problem: Problem, fraction: float, seed: int = 0):
    """True pairs with ``fraction`` of them removed and as many wrong cross-view pairs added."""
    rng = np.random.default_rng(seed)
    pairs = true_pair_list(problem)
    k = max(1, int(round(fraction * len(pairs))))
    keep = [pairs[i] for i in sorted(rng.choice(len(pairs), len(pairs) - k, replace=False))]
    gt, view, n = problem.gt_track, problem.view_index, problem.n_keypoints
    wrong = set()
    while len(wrong) < k:
        a, b = (int(x) for x in rng.integers(n, size=2))
        if view[a] != view[b] and (gt[a] != gt[b] or gt[a] < 0):
            wrong.add((min(a, b), max(a, b)))
    return keep + sorted(wrong)
