"""What a solver carries from one window of a stream to the next.

A matcher node, and an offline replay of the same bag, solve a *stream* of windows. Anything
learnt from earlier windows lives in one :class:`StreamState` per stream and is used in window
order, so the node and the offline path (:func:`solve_stream`) give the same answers for the
same windows. Today that is the rig memory (:mod:`gcn_match_ros.edges.rig_memory`): the
two-view models of camera pairs, re-checked on every window and re-fitted only when they fail.
"""
from __future__ import annotations

import dataclasses
from typing import Iterable, Iterator

from .edges.rig_memory import RigMemory
from .problem import Problem, Result

__all__ = ["StreamState", "solve_stream"]


@dataclasses.dataclass
class StreamState:
    """Per-stream state; a new one starts the stream afresh.

    Attributes:
        rig: two-view models by camera pair (windows whose problems name their cameras).
    """

    rig: RigMemory = dataclasses.field(default_factory=RigMemory)


def solve_stream(solver, problems: Iterable[Problem], state: StreamState = None) -> Iterator[Result]:
    """Solve ``problems`` in order as one stream (what the node does with its windows).

    Args:
        solver: a :class:`gcn_match_ros.solvers.base.Solver`.
        problems: the windows, in stream order.
        state: the stream's state (a new one if None).
    """
    state = state if state is not None else StreamState()
    for problem in problems:
        yield solver.solve(problem, stream=state)
