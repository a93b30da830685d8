"""Where the time of one solve goes: named stages, measured only when someone records.

``with stage("geometry"): ...`` marks a stage anywhere in the matching code. It costs
nothing unless a :class:`StageTimes` is recording in the same thread (or task): then its
wall time is added to that stage, *exclusive* of stages nested inside it, so the stages of
one solve add up to its total. :meth:`gcn_match_ros.solvers.base.Solver.solve` records every
solve and returns the stages in ``Result.timings``.
"""
from __future__ import annotations

import contextlib
import contextvars
import time
from typing import Dict, Iterator, List, Optional

__all__ = ["StageTimes", "stage", "add_to_active"]

_ACTIVE: "contextvars.ContextVar[Optional[StageTimes]]" = contextvars.ContextVar("gcn_match_ros_stages",
                                                                                  default=None)


class StageTimes:
    """Seconds per stage name, exclusive of nested stages (:func:`stage`)."""

    def __init__(self) -> None:
        self.seconds: Dict[str, float] = {}
        self._stack: List[List[float]] = []  # [start, time spent in nested stages]

    @contextlib.contextmanager
    def recording(self) -> Iterator["StageTimes"]:
        """Make this the recorder of :func:`stage` calls in the current context."""
        token = _ACTIVE.set(self)
        try:
            yield self
        finally:
            _ACTIVE.reset(token)

    def add(self, seconds: Dict[str, float]) -> None:
        """Add stage times measured by another recorder (e.g. of work on another thread)."""
        for name, value in seconds.items():
            self.seconds[name] = self.seconds.get(name, 0.0) + value

    def _enter(self) -> None:
        self._stack.append([time.perf_counter(), 0.0])

    def _exit(self, name: str) -> None:
        start, nested = self._stack.pop()
        total = time.perf_counter() - start
        self.seconds[name] = self.seconds.get(name, 0.0) + total - nested
        if self._stack:
            self._stack[-1][1] += total


@contextlib.contextmanager
def stage(name: str) -> Iterator[None]:
    """Count the enclosed time as stage ``name`` of the active :class:`StageTimes`, if any."""
    times = _ACTIVE.get()
    if times is None:
        yield
        return
    times._enter()
    try:
        yield
    finally:
        times._exit(name)


def add_to_active(seconds: Dict[str, float]) -> None:
    """Add stage times measured on another thread to this context's recorder, if one is active.

    Such stages overlap the recorder's own, so a solve's stages may then add up to more than
    its wall time."""
    times = _ACTIVE.get()
    if times is not None:
        times.add(seconds)
