"""Shared fixtures: paths to ../shared and small random problems."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gcn_match_ros.problem import Problem

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
