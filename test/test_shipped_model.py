"""The shipped model loads safely, beats nn on a held-out problem, and gives cycle-consistent tracks."""
from pathlib import Path

import numpy as np
import pytest
import torch

from gcn_match_ros.metrics import score_result
from gcn_match_ros.model import load_checkpoint
from gcn_match_ros.problem import load_problem
from gcn_match_ros.rounding import is_cycle_consistent
from gcn_match_ros.solvers import get_solver
from gcn_match_ros.solvers.gcn import DEFAULT_CHECKPOINT

# Oxford is never trained on (no poses): a held-out problem.
HELD_OUT = Path(__file__).resolve().parents[2] / "shared" / "reference" / "oxford-dev" / "problems" / \
    "oxford_boat_sift_123.npz"


def test_shipped_model_loads_weights_only():
    assert DEFAULT_CHECKPOINT.is_file()
    assert DEFAULT_CHECKPOINT.stat().st_size < 10 * 2 ** 20
    payload = torch.load(DEFAULT_CHECKPOINT, map_location="cpu", weights_only=True)
    assert payload["format"] == "gcn_match_ros/gcn-checkpoint"
    model, meta = load_checkpoint(DEFAULT_CHECKPOINT)
    assert getattr(model, "edge_head", None) is not None


@pytest.mark.skipif(not HELD_OUT.is_file(), reason="shared reference problems not available")
def test_shipped_model_beats_nn_on_held_out_and_is_cycle_consistent():
    torch.set_num_threads(1)
    problem = load_problem(HELD_OUT)
    gcn = get_solver("gcn").solve(problem)
    nn = get_solver("nn").solve(problem)
    f_gcn, f_nn = score_result(problem, gcn)["F1"], score_result(problem, nn)["F1"]
    assert f_gcn > f_nn + 0.02, (f_gcn, f_nn)
    assert is_cycle_consistent(gcn.track, problem.view_index)
    # at most one keypoint per view in every track
    t = gcn.track
    keep = t >= 0
    pairs = np.stack([t[keep], problem.view_index[keep]], 1)
    assert np.unique(pairs, axis=0).shape[0] == pairs.shape[0]
