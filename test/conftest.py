"""Shared fixtures: paths to ../shared, small random problems and camera frames.

ROS tests talk DDS on this machine only: discovery is confined to it here, before any test
module imports rclpy (``./run.sh test`` sets the same).
"""
from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

import numpy as np
import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # no traffic leaves the machine
os.environ.pop("ROS_LOCALHOST_ONLY", None)
if not os.environ.get("ROS_LOG_DIR"):
    os.environ["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix="gcn_match_ros-test-roslog-")

from gcn_match_ros.problem import Problem  # noqa: E402
from gcn_match_ros.stamps import seconds_to_ns  # noqa: E402
from gcn_match_ros.windowing import Frame  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
REFERENCE_PROBLEMS = SHARED / "reference" / "oxford-dev" / "problems"


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


def look_at(centre: np.ndarray, target: np.ndarray) -> tuple:
    """World->camera R, t for a camera at ``centre`` looking at ``target`` (y down)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross([0.0, 0.0, -1.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ centre


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


def domain_id() -> int:
    """A random ROS domain for one test's DDS traffic."""
    return random.SystemRandom().randint(1, 100)


class PermutedScene:
    """Descriptors of ``points`` scene points; every camera sees all of them permuted, with
    noise, plus a few distractors (gt -1). Keypoint positions are per point + pixel noise."""

    def __init__(self, points: int = 60, dim: int = 128, noise: float = 0.05, distractors: int = 5,
                 seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.base = np.abs(self.rng.normal(size=(points, dim)))
        self.xy = self.rng.uniform(20, 620, size=(points, 2))
        self.points, self.dim, self.noise, self.distractors = points, dim, noise, distractors

    def frame(self, cam: str, seconds: float):
        """(Frame stamped ``seconds``, its (N,) ground truth)."""
        rng, p = self.rng, self.points
        perm = rng.permutation(p)
        desc = np.abs(self.base[perm] + self.noise * rng.normal(size=(p, self.dim)))
        xy = self.xy[perm] + rng.normal(scale=2.0, size=(p, 2))
        if self.distractors:
            desc = np.vstack([desc, np.abs(rng.normal(size=(self.distractors, self.dim)))])
            xy = np.vstack([xy, rng.uniform(20, 620, size=(self.distractors, 2))])
        gt = np.concatenate([perm, -np.ones(self.distractors, np.int64)])
        f = Frame(camera_id=cam, stamp_ns=seconds_to_ns(seconds), keypoints=xy.astype(np.float32),
                  descriptors=desc.astype(np.float32), frame_id=f"{cam}_optical_frame",
                  scales=np.full(len(gt), 3.0, np.float32), orientations=np.zeros(len(gt), np.float32),
                  K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), image_size=(640, 480),
                  descriptor_name="sift")
        return f, gt
