"""Tests of gcn_match_ros.stream beyond the rig memory (test_edges_rig_memory): where the
landmark association runs."""
import threading

import numpy as np

from gcn_match_ros import solvers
from gcn_match_ros.data.rig_sequence import RigSequenceConfig, rig_sequence
from gcn_match_ros.stream import StreamState, solve_window


def test_landmark_candidates_beside_the_solve_give_the_ids_of_after_it():
    problems, _, stamps = rig_sequence(RigSequenceConfig(n_cameras=2, n_windows=4, n_points=300), rng=2)
    solver = solvers.create("gcn")
    ids, threads = {}, {}
    for beside in (True, False):
        state = StreamState()
        prepare = state.landmarks.prepare
        state.landmarks.prepare = lambda *a: threads.setdefault(beside, set()).add(
            threading.current_thread().name) or prepare(*a)
        ids[beside] = []
        for p, stamp in zip(problems, stamps):
            state.spare_second_thread = beside   # else set from the last solve's wait
            ids[beside].append(solve_window(solver, p, state, stamp)[1].ids)
    assert all(name.startswith("gcn_match_ros-alongside") for name in threads[True])
    assert threads[False] == {threading.current_thread().name}
    assert sum((i >= 0).sum() for i in ids[True][1:]) > 100   # windows after the first continue landmarks
    for a, b in zip(ids[True], ids[False]):
        np.testing.assert_array_equal(a, b)


def test_the_second_thread_counts_as_spare_only_when_the_solve_did_not_wait_for_it():
    problems, _, stamps = rig_sequence(RigSequenceConfig(n_cameras=2, n_windows=1, n_points=100), rng=2)
    state = StreamState()
    solve_window(solvers.create("nn"), problems[0], state, stamps[0])   # nn runs nothing there
    assert not state.spare_second_thread
