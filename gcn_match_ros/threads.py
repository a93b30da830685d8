"""CPU threads of a process that solves windows: numpy's BLAS runs on one thread, and one
part of a window can run on a second thread beside the rest.

torch runs the network on its own thread pool (one thread per core). numpy's OpenBLAS keeps a
second pool of as many threads for the matrix products of the rest of a window (descriptor
products of the landmarks, two-view fits). On a 2-core robot computer both pools' threads spin
while they wait and take the cores from each other: a 4 x 500 window of the matcher node's path
took 134 ms with numpy's default and 66 ms with one BLAS thread (same outputs). The entry points
that solve (the matcher node, ``gcn-match``) call :func:`single_blas_thread` once at start-up.

:func:`alongside` runs one function on the process's second thread while the caller goes on:
the ``gcn`` solver's candidate edges (two-view fits, compiled loops that release the GIL) beside
its graph and network (torch, which releases it too). On 2 cores: the matcher node's 4 x 500
p95 latency 125 -> 80 ms (benchmarks/results/node_latency.md), the offline stream solve 71 -> 63
ms (stage_breakdown.md; the two threads slow each other, so the gain varies between runs).
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import threading
from typing import Any, Callable, Iterator, Optional

from threadpoolctl import threadpool_limits

from .timing import StageTimes, add_to_active

__all__ = ["single_blas_thread", "alongside", "Pending"]

_SECOND_THREAD = "gcn_match_ros-alongside"
_pool: Optional[concurrent.futures.ThreadPoolExecutor] = None
_pool_lock = threading.Lock()


def single_blas_thread() -> None:
    """Limit every BLAS library loaded in this process (numpy's OpenBLAS) to one thread, for
    the rest of the process; torch's own pool is left as it is."""
    threadpool_limits(limits=1, user_api="blas")


class Pending:
    """The result of a function started by :func:`alongside`."""

    def __init__(self, fn: Callable[..., Any], args: tuple, future: Optional[concurrent.futures.Future]) -> None:
        self._fn, self._args, self._future = fn, args, future
        self._done = False
        self._value: Any = None

    def result(self) -> Any:
        """The function's return value (its exception re-raised), waiting for it if need be;
        the stages it timed (:mod:`gcn_match_ros.timing`) are added to the caller's recorder."""
        if not self._done:
            if self._future is None:  # not started: run here, now, as sequential code would
                self._value = self._fn(*self._args)
            else:
                self._value, seconds = self._future.result()
                add_to_active(seconds)
            self._done = True
        return self._value


@contextlib.contextmanager
def alongside(fn: Callable[..., Any], *args: Any, parallel: bool = True) -> Iterator[Pending]:
    """Run ``fn(*args)`` on the process's second thread while the ``with`` body runs.

    The block does not end before ``fn`` has, even when the body raises, so nothing ``fn``
    touches (a stream's rig memory) is used by two windows at once. One second thread serves
    the process: calls from different threads queue for it. ``parallel=False`` — or a call
    from that thread itself, which would otherwise wait for itself — runs ``fn`` only when
    :meth:`Pending.result` is asked for, on the caller's thread: the same results, sequentially.

    Yields:
        :class:`Pending`, whose ``result()`` gives ``fn``'s return value.
    """
    if not parallel or threading.current_thread().name.startswith(_SECOND_THREAD):
        yield Pending(fn, args, None)
        return
    future = _second_thread().submit(_timed, fn, args)
    try:
        yield Pending(fn, args, future)
    finally:
        concurrent.futures.wait([future])


def _timed(fn: Callable[..., Any], args: tuple):
    """fn(*args) and the stages it timed, on the second thread (which has no recorder of its own)."""
    times = StageTimes()
    with times.recording():
        value = fn(*args)
    return value, times.seconds


def _second_thread() -> concurrent.futures.ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=_SECOND_THREAD)
        return _pool
