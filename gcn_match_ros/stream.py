"""What a solver carries from one window of a stream to the next.

A matcher node, and an offline replay of the same bag, solve a *stream* of windows. Anything
learnt from earlier windows lives in one :class:`StreamState` per stream and is used in window
order, so the node and the offline path (:func:`solve_stream`) give the same answers for the
same windows:

- the rig memory (:mod:`gcn_match_ros.edges.rig_memory`): the two-view models of camera pairs,
  re-checked on every window and re-fitted only when they fail;
- the landmarks (:mod:`gcn_match_ros.landmarks`): ids of 3-D points that persist across
  windows (:func:`solve_window` gives every keypoint its landmark).
"""
from __future__ import annotations

import dataclasses
import time
from typing import Iterable, Iterator, Optional, Sequence, Tuple

import numpy as np

from .edges.rig_memory import RigMemory
from .landmarks import LandmarkTracker
from .problem import Problem, Result
from .threads import deferred, kept_apart

__all__ = ["StreamState", "WindowLandmarks", "solve_window", "solve_stream"]


@dataclasses.dataclass
class StreamState:
    """Per-stream state; a new one starts the stream afresh.

    Attributes:
        rig: two-view models by camera pair (windows whose problems name their cameras).
        landmarks: the live landmarks and their ids.
    """

    rig: RigMemory = dataclasses.field(default_factory=RigMemory)
    landmarks: LandmarkTracker = dataclasses.field(default_factory=LandmarkTracker)


@dataclasses.dataclass
class WindowLandmarks:
    """The landmark of every keypoint of one window.

    Shapes: ids (N,) int64 (-1: none); ages_ns (N,) int64 nanoseconds since the landmark was
    first seen (-1: none). ``seconds``: the time the landmarks took after the solve: the
    search's chunks still left (the search runs beside the solve where the solver leaves the
    second thread idle) and the association.
    """

    ids: np.ndarray
    ages_ns: np.ndarray
    seconds: float = 0.0

    @property
    def ages_s(self) -> np.ndarray:
        """(N,) float64 ages in seconds, -1 where there is no landmark (as ``MatchWindow`` carries them)."""
        return np.where(self.ids >= 0, self.ages_ns * 1e-9, -1.0)


def solve_window(solver, problem: Problem, state: StreamState, stamp_ns: int,
                 landmarks: bool = True) -> Tuple[Result, Optional[WindowLandmarks]]:
    """Solve one window of a stream (rig memory) and give its keypoints their landmarks.

    Args:
        solver: a :class:`gcn_match_ros.solvers.base.Solver`.
        stamp_ns: the window's capture time (its newest view stamp), for landmark ages and
            retirement. A problem without ``camera_ids`` gets no landmarks (all -1).
        landmarks: False: no association at all (None instead of the landmarks; the tracker
            is not touched), for consumers that need only the window's own tracks.
    """
    if not landmarks:
        return solver.solve(problem, stream=state), None
    if problem.camera_ids is None:
        none = np.full(problem.n_keypoints, -1, np.int64)
        return solver.solve(problem, stream=state), WindowLandmarks(none, none.copy())
    # The landmark search needs no tracks: it runs on the second thread once the solve leaves
    # that thread idle (Solver.solve's ``beside``), this thread takes the chunks still left once
    # the solve is done, and the association then takes its result.
    # The solver's placement of its two threads (Solver.keeps_threads_apart) lasts to the end of the search.
    search = state.landmarks.search_job(problem.camera_ids, problem.view_offsets, problem.keypoints,
                                        problem.descriptors, int(stamp_ns))
    with kept_apart(solver.keeps_threads_apart), deferred(search.help) as beside:
        result = solver.solve(problem, stream=state, beside=beside)
        start = time.perf_counter()
        beside.start()  # where the solver left it unstarted (one-thread solves): both threads search
        searched = search.result()
    ids, ages = state.landmarks.associate(searched, result.track)
    return result, WindowLandmarks(ids, ages, time.perf_counter() - start)


def solve_stream(solver, problems: Iterable[Problem], stamps_ns: Sequence[int],
                 state: Optional[StreamState] = None) -> Iterator[Tuple[Result, WindowLandmarks]]:
    """Solve ``problems`` in order as one stream, what the node does with its windows.

    Args:
        problems: the windows, in stream order; stamps_ns: their capture times.
        state: the stream's state (a new one if None).
    """
    state = state if state is not None else StreamState()
    for problem, stamp in zip(problems, stamps_ns):
        yield solve_window(solver, problem, state, stamp)
