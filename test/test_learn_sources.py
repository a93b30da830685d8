"""Tests of gcn_match_ros.learn.sources: problem-file and generated training data, shuffled and seekable."""
import numpy as np
import pytest

from gcn_match_ros.learn.sources import ProblemFileSource, SyntheticSource
from gcn_match_ros.problem import save_problem

from conftest import posed_problem


def test_sources(tmp_path):
    rng = np.random.default_rng(1)
    for i in range(3):
        save_problem(posed_problem(rng), tmp_path / f"p{i}.npz")
    src = ProblemFileSource(tmp_path, shuffle=True, seed=3)
    seq = [p.name for p, _ in zip(src(), range(7))]
    assert sorted(seq[:3]) == ["p0", "p1", "p2"] and sorted(seq[3:6]) == ["p0", "p1", "p2"]
    assert [p.name for p, _ in zip(src(4), range(3))] == seq[4:7]  # seekable
    once = ProblemFileSource([tmp_path / "p1.npz", tmp_path / "p0.npz"], shuffle=False, cycle=False)
    assert [p.name for p in once()] == ["p1", "p0"]
    syn = SyntheticSource(posed_problem, seed=5)
    a = [p.keypoints for p, _ in zip(syn(), range(3))]
    b = next(syn(2)).keypoints
    assert np.array_equal(a[2], b)
    with pytest.raises(ValueError, match="no such file or directory"):
        ProblemFileSource(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no problem files"):
        ProblemFileSource(tmp_path / "empty")
