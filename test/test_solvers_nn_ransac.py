"""Tests of gcn_match_ros.solvers.nn_ransac: the geometric baselines' settings."""
import numpy as np
import pytest

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.rounding import is_cycle_consistent


def _pairs(result, n):
    return set((result.pair_rows * n + result.pair_cols).tolist())


@pytest.mark.parametrize("setting, bad, error, strict", [
    ("epipolar_ratio", "epipolar_ratio=-1", "epipolar_ratio", "epipolar_ratio=0.5"),
    ("neighbours", "neighbours=4,min_shared_neighbours=5", "neighbourhood", "neighbours=8,min_shared_neighbours=8"),
])
def test_guided_rules_against_repetitions_only_remove_pairs(setting, bad, error, strict):
    """With ``guided``, the rules gcn uses against repetitions (the ratio along the epipolar line,
    the neighbourhood rule) drop pairs before the tracks are merged: a subset of the pairs
    without them, fewer with sharp descriptors and a strict setting; off by default; bad
    settings are refused."""
    assert getattr(solvers.create("nn-ransac:guided=true").config, setting) == 0
    with pytest.raises(ValueError, match=error):
        solvers.create(f"nn-ransac:guided=true,{bad}")
    sharp = synthetic.random_scene_problem(synthetic.rome16k(3, descriptor_noise=0.5), np.random.default_rng([11, 0]))
    n = sharp.n_keypoints
    plain = solvers.create("nn-ransac:guided=true").solve(sharp)
    judged = solvers.create(f"nn-ransac:guided=true,{strict}").solve(sharp)
    assert _pairs(judged, n) < _pairs(plain, n)
    assert is_cycle_consistent(judged.track, sharp.view_index)
