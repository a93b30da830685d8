"""Tests of gcn_match_ros.solvers.nn_ransac: the geometric baselines' settings."""
import numpy as np
import pytest

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.rounding import is_cycle_consistent


def _pairs(result, n):
    return set((result.pair_rows * n + result.pair_cols).tolist())


def test_guided_epipolar_ratio_only_removes_pairs():
    """With ``guided``, the ambiguity rule gcn uses drops pairs before the tracks are merged: a
    subset of the pairs without it, fewer with sharp descriptors and a strict ratio; off by
    default; a negative ratio is refused."""
    assert solvers.create("nn-ransac:guided=true").config.epipolar_ratio == 0.0
    with pytest.raises(ValueError, match="epipolar_ratio"):
        solvers.create("nn-ransac:guided=true,epipolar_ratio=-1")
    sharp = synthetic.random_scene_problem(synthetic.rome16k(3, descriptor_noise=0.5), np.random.default_rng([11, 0]))
    n = sharp.n_keypoints
    plain = solvers.create("nn-ransac:guided=true").solve(sharp)
    strict = solvers.create("nn-ransac:guided=true,epipolar_ratio=0.5").solve(sharp)
    assert _pairs(strict, n) < _pairs(plain, n)
    assert is_cycle_consistent(strict.track, sharp.view_index)
