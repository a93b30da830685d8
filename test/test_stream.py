"""Tests of gcn_match_ros.stream: a stream's windows solved one after another (rig memory, landmarks)."""
import dataclasses
import gc

import numpy as np
import pytest
import torch

from gcn_match_ros import solvers
from gcn_match_ros.data import synthetic
from gcn_match_ros.stream import StreamState, solve_window


@pytest.mark.parametrize("spec", ["gcn", "gcn:parallel=false", "nn-ransac:guided=true", "nn"])
def test_a_streams_window_leaves_no_reference_cycles_behind(one_torch_thread, spec):
    """Everything a window's solve and landmarks made is freed by reference counting once the
    caller lets go: a cycle (the candidate job's view-pair tasks, bound methods of the job, once
    held it) keeps a window's similarity blocks and edges, ~29 MB at 8 x 500, until the cyclic
    collector's rare full pass: the process grew and faulted its pages in again."""
    problem = synthetic.random_scene_problem(synthetic.rome16k(4, n_points=120), np.random.default_rng(3))
    problem = dataclasses.replace(problem, camera_ids=("cam0", "cam1", "cam2", "cam3"))
    solver, state = solvers.create(spec), StreamState()
    solve_window(solver, problem, state, 0)  # first-call caches (model, compiled code) made
    gc.collect()
    gc.disable()
    gc.set_debug(gc.DEBUG_SAVEALL)  # what the collector finds unreachable stays in gc.garbage
    try:
        for k in range(1, 3):
            result, landmarks = solve_window(solver, problem, state, k * 10**8)
            assert (landmarks.ids >= 0).any()
            del result, landmarks
        gc.collect()
        ours = [type(o).__qualname__ for o in gc.garbage
                if type(o).__module__.startswith("gcn_match_ros") or isinstance(o, (np.ndarray, torch.Tensor))]
        assert ours == []
    finally:
        gc.set_debug(0)
        gc.garbage.clear()
        gc.enable()
