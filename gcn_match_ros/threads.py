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

The cores are shared out between the two threads, since torch's OpenMP workers spin while
they wait and take a core from whatever else runs. The second thread's torch ops (descriptor
products) run on one thread: a second thread opening an OpenMP pool of its own gives the process
more OpenMP threads than cores, and libgomp then stops spinning between parallel regions for the
rest of the process (the 4 x 500 network alone: 5 -> 10 ms after one torch op on another thread);
the products are bitwise the same on one thread or two. While ``fn`` runs, the caller's torch
keeps one core fewer (on 2 cores: one), and gets it back when ``fn``'s result is taken: the 4 x
500 stream solve 45 -> 34 ms, solve outputs identical.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import threading
from typing import Any, Callable, Iterator, Optional

import torch
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

    def __init__(self, fn: Callable[..., Any], args: tuple, future: Optional[concurrent.futures.Future],
                 caller_threads: Optional[int] = None) -> None:
        self._fn, self._args, self._future = fn, args, future
        self._caller_threads = caller_threads  # the caller's torch threads, to restore; None: not lowered
        self._done = False
        self._value: Any = None

    def result(self) -> Any:
        """The function's return value (its exception re-raised), waiting for it if need be;
        the stages it timed (:mod:`gcn_match_ros.timing`) are added to the caller's recorder."""
        if not self._done:
            if self._future is None:  # not started: run here, now, as sequential code would
                self._value = self._fn(*self._args)
            else:
                try:
                    self._value, seconds = self._future.result()
                finally:
                    self._give_back_core()
                add_to_active(seconds)
            self._done = True
        return self._value

    def _give_back_core(self) -> None:
        """The caller's torch threads back (once)."""
        if self._caller_threads is not None:
            torch.set_num_threads(self._caller_threads)
            self._caller_threads = None


@contextlib.contextmanager
def alongside(fn: Callable[..., Any], *args: Any, parallel: bool = True) -> Iterator[Pending]:
    """Run ``fn(*args)`` on the process's second thread while the ``with`` body runs.

    Until ``fn``'s result is taken (or the block ends), the caller's torch runs on one thread
    fewer (``torch.set_num_threads``, which also sets the count of threads that start using torch
    meanwhile). The block does not end before ``fn`` has, even when the body raises, so nothing ``fn``
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
    threads = torch.get_num_threads()
    if threads > 1:  # one core fewer for the caller's torch while fn has one
        torch.set_num_threads(threads - 1)
    pending = Pending(fn, args, future, threads if threads > 1 else None)
    try:
        yield pending
    finally:
        concurrent.futures.wait([future])
        pending._give_back_core()


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
            threads = torch.get_num_threads()
            _pool = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=_SECOND_THREAD,
                                                          initializer=_one_torch_thread)
            _pool.submit(int).result()  # the initializer runs now
            # torch.set_num_threads also sets the count every thread takes at its first torch op
            torch.set_num_threads(threads)
        return _pool


def _one_torch_thread() -> None:
    """This thread's torch ops on one thread; the count taken first, so that torch's lazy
    per-thread set-up cannot later replace it with the process's count."""
    torch.get_num_threads()
    torch.set_num_threads(1)
