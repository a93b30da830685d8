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
its graph and network (torch, which releases it too). :func:`deferred` leaves the start to whoever
knows when that thread is idle: a stream's landmark search waits for the solver to start it once
its candidate edges are done (:func:`gcn_match_ros.stream.solve_window`). On 2 cores: the matcher
node's 4 x 500 p95 latency 125 -> 80 ms (benchmarks/results/node_latency.md), the offline stream
solve 71 -> 63 ms (stage_breakdown.md; the two threads slow each other, so the gain varies between
runs). :class:`SharedTasks` is work cut into tasks that whichever thread is free takes, so that a
thread that would wait for the other helps instead (the candidate edges' view pairs, the landmark
search's chunks of keypoints).

The cores are shared out between the two threads, since torch's OpenMP workers spin while
they wait and take a core from whatever else runs. The second thread's torch ops (descriptor
products) run on one thread: a second thread opening an OpenMP pool of its own gives the process
more OpenMP threads than cores, and libgomp then stops spinning between parallel regions for the
rest of the process (the 4 x 500 network alone: 5 -> 10 ms after one torch op on another thread);
the products are bitwise the same on one thread or two. While ``fn`` runs, the caller's torch
keeps one core fewer (on 2 cores: one), and gets it back when ``fn``'s result is taken: the 4 x
500 stream solve 45 -> 34 ms, solve outputs identical.

:func:`kept_apart` keeps a window's two threads on two CPUs while it is solved, the CPU the
solving thread is on and another, chosen anew for every window; :func:`pinned_solve_threads`
keeps them on two given CPUs. A kernel that packs threads onto few CPUs while the load is light
(this project's 2-core VM: its guest kernel runs with ``sched_vcpu_pack``) puts the second thread
on the first one's CPU when a window starts after a pause, and spreads them only under sustained
load: at 10 Hz a 4 x 500 window then runs its two threads on one core for much of its time (p95 51
ms against 33 kept apart, benchmarks/results/idle_wake.md). Between windows the threads are the
OS's to place, so a CPU another process takes holds a window's thread for one window at most.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import os
import threading
from typing import Any, Callable, Iterator, List, Optional, Sequence, Tuple

import torch
from threadpoolctl import threadpool_limits

from .libc import c_function
from .timing import StageTimes, add_to_active

__all__ = ["single_blas_thread", "solve_cpus", "pinned_solve_threads", "kept_apart", "alongside", "deferred",
           "Pending", "SharedTasks", "one_torch_thread"]

_SECOND_THREAD = "gcn_match_ros-alongside"
_pool: Optional[concurrent.futures.ThreadPoolExecutor] = None
_pool_lock = threading.Lock()
_second_tid: Optional[int] = None  # the second thread's id for the OS (sched_setaffinity)
_second_placed = False  # inside a pinned_solve_threads block
_cores_taken = 0     # started functions whose results are not yet taken (_take_core)
_threads_before = 1  # the caller's torch threads before the first of them
# the CPU the calling thread runs on, where threads can be placed
_sched_getcpu = c_function("sched_getcpu") if hasattr(os, "sched_setaffinity") else None


def single_blas_thread() -> None:
    """Limit every BLAS library loaded in this process (numpy's OpenBLAS) to one thread, for
    the rest of the process; torch's own pool is left as it is."""
    threadpool_limits(limits=1, user_api="blas")


def solve_cpus(first_cpu: int) -> Tuple[int, int]:
    """The two CPUs :func:`pinned_solve_threads` puts the solve's threads on: ``first_cpu`` and the
    next CPU this process may use (its main thread's CPUs) after it, in CPU order, wrapping around.

    Raises:
        ValueError: ``first_cpu`` not among the process's CPUs, fewer than two of them, or no
            thread placement on this platform.
    """
    if not hasattr(os, "sched_setaffinity"):
        raise ValueError("placing threads on CPUs needs os.sched_setaffinity (Linux)")
    allowed = sorted(os.sched_getaffinity(os.getpid()))
    if first_cpu not in allowed:
        raise ValueError(f"CPU {first_cpu} is not one this process may use "
                         f"(CPUs {', '.join(str(c) for c in allowed)})")
    if len(allowed) < 2:
        raise ValueError(f"two threads need two CPUs; this process may use only CPU {allowed[0]}")
    return first_cpu, allowed[(allowed.index(first_cpu) + 1) % len(allowed)]


@contextlib.contextmanager
def pinned_solve_threads(first_cpu: int) -> Iterator[Tuple[int, int]]:
    """Inside the block, the calling thread (the one that solves) runs on CPU ``first_cpu`` alone
    and the process's second thread (:func:`alongside`) on the next one (:func:`solve_cpus`);
    see the module docstring for why. torch runs on one thread meanwhile: the OpenMP workers it
    starts would inherit the calling thread's CPU and share it with that thread. Both threads'
    CPUs and torch's thread count are as before once the block ends.

    Yields:
        (the calling thread's CPU, the second thread's CPU).

    Raises:
        ValueError: as :func:`solve_cpus`, or another thread's block has placed the second
            thread; before anything is changed.
    """
    global _second_placed
    first, second = solve_cpus(first_cpu)
    _second_thread()
    with _pool_lock:  # one placement of the second thread at a time, so each gives back what it found
        if _second_placed:
            raise ValueError("the second thread is placed for another thread's solves")
        _second_placed = True
    try:
        mine, theirs = os.sched_getaffinity(0), os.sched_getaffinity(_second_tid)
        torch_threads = torch.get_num_threads()
        try:
            os.sched_setaffinity(0, {first})  # 0: the calling thread
            os.sched_setaffinity(_second_tid, {second})
            torch.set_num_threads(1)
            yield first, second
        finally:
            os.sched_setaffinity(0, mine)
            os.sched_setaffinity(_second_tid, theirs)
            torch.set_num_threads(torch_threads)
    finally:
        with _pool_lock:
            _second_placed = False


@contextlib.contextmanager
def kept_apart(enabled: bool = True) -> Iterator[None]:
    """Inside the block, the calling thread runs on the CPU it is on now and the process's second
    thread on the next CPU the process may use (:func:`pinned_solve_threads` for that CPU), for a
    solve that runs on both (see the module docstring for why); all as before once the block ends.

    Nothing is placed when ``enabled`` is False, when the calling thread may run on one CPU only
    (inside another ``kept_apart`` of this thread, :func:`pinned_solve_threads`, ``taskset``), when
    the process has fewer than two CPUs, or where threads cannot be placed; nor when the CPUs
    change under it meanwhile (the OS then places the threads, as it does outside the block).
    """
    with contextlib.ExitStack() as placement:
        cpu = _this_cpu() if enabled else None
        if cpu is not None:
            try:
                placement.enter_context(pinned_solve_threads(cpu))
            except (ValueError, OSError):
                pass
        yield


def _this_cpu() -> Optional[int]:
    """The CPU the calling thread runs on, if it may run on others too and is not the second
    thread itself; else None."""
    if (_sched_getcpu is None or threading.current_thread().name.startswith(_SECOND_THREAD)
            or len(os.sched_getaffinity(0)) < 2):
        return None
    cpu = _sched_getcpu()
    return cpu if cpu >= 0 else None


class Pending:
    """``fn(*args)``, run on the process's second thread once :meth:`start`-ed, else on the caller's
    thread when its :meth:`result` is asked for (made by :func:`deferred` and :func:`alongside`)."""

    def __init__(self, fn: Callable[..., Any], args: tuple, parallel: bool = True) -> None:
        self._fn, self._args = fn, args
        # a call from the second thread itself would wait for itself
        self._parallel = parallel and not threading.current_thread().name.startswith(_SECOND_THREAD)
        self._future: Optional[concurrent.futures.Future] = None
        self._holds_core = False  # the caller's torch runs on one thread fewer for it
        self._done = False
        self._value: Any = None

    def start(self) -> None:
        """Queue ``fn`` for the second thread now (it runs after what was queued before); from
        then until its result is taken, the caller's torch runs on one thread fewer
        (:func:`_take_core`). Nothing when already started or done, or when made with
        ``parallel=False``."""
        if self._future is not None or self._done or not self._parallel:
            return
        self._future = _second_thread().submit(_timed, self._fn, self._args)
        _take_core()
        self._holds_core = True

    def withdraw(self) -> bool:
        """Take back a start whose ``fn`` has not begun on the second thread (work queued before
        it still runs there): it then runs at :meth:`result`, on the caller's thread. Returns
        True when withdrawn."""
        if self._future is None or not self._future.cancel():
            return False
        self._future = None
        self._release_core()
        return True

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
                    self._release_core()
                add_to_active(seconds)
            self._done = True
        return self._value

    def _finish(self) -> None:
        """Wait for a started ``fn`` and give its core back."""
        if self._future is not None:
            concurrent.futures.wait([self._future])
        self._release_core()

    def _release_core(self) -> None:
        if self._holds_core:
            self._holds_core = False
            _give_back_core()


class SharedTasks:
    """Independent tasks that whichever threads take part run, each exactly once: :meth:`help`
    runs tasks not yet taken until none is left, :meth:`results` helps, then waits for the tasks
    other threads took. A thread that would otherwise wait for work on the second thread helps
    instead (the ``gcn`` solver's candidate edges, a stream's landmark search); each task's
    result is the same whoever ran it. A task is let go of once taken, so tasks may be bound
    methods of the object that holds them without keeping it alive in a reference cycle.

    Args:
        tasks: callables without arguments.
        order: the positions of ``tasks`` in the order they are taken (default: as given);
            :meth:`results` keeps the order of ``tasks``.
    """

    def __init__(self, tasks: Sequence[Callable[[], Any]], order: Optional[Sequence[int]] = None) -> None:
        self._tasks = list(tasks)
        self._order = list(range(len(self._tasks))) if order is None else [int(k) for k in order]
        if sorted(self._order) != list(range(len(self._tasks))):
            raise ValueError(f"order must hold each of the {len(self._tasks)} task positions once")
        self._results: List[Any] = [None] * len(self._tasks)
        self._errors: List[BaseException] = []
        self._taken = 0
        self._finished = 0
        self._changed = threading.Condition()

    def __len__(self) -> int:
        return len(self._tasks)

    def help(self) -> None:
        """Run tasks not yet taken, on this thread, until none is left (or one has failed)."""
        while True:
            with self._changed:
                if self._taken == len(self._tasks) or self._errors:
                    return
                k = self._order[self._taken]
                self._taken += 1
                # let go of once taken (class docstring): a cycle would keep a window's arrays
                # until the cyclic collector's rare full pass
                task, self._tasks[k] = self._tasks[k], None
            try:
                self._results[k] = task()
            except BaseException as exc:  # handed to the thread that asks for the results
                with self._changed:
                    self._errors.append(exc)
            finally:
                with self._changed:
                    self._finished += 1
                    self._changed.notify_all()

    def results(self) -> List[Any]:
        """Every task's return value, in the order of ``tasks`` (the first error re-raised),
        helping meanwhile."""
        self.help()
        with self._changed:
            self._changed.wait_for(lambda: self._finished == self._taken)
            if self._errors:
                raise self._errors[0]
        return list(self._results)


def _take_core() -> None:
    """One torch thread fewer for the caller while any started function has not been taken (the
    first one lowers ``torch.set_num_threads``, which also sets the count of threads that start
    using torch meanwhile)."""
    global _cores_taken, _threads_before
    with _pool_lock:
        if _cores_taken == 0:
            _threads_before = torch.get_num_threads()
            if _threads_before > 1:
                torch.set_num_threads(_threads_before - 1)
        _cores_taken += 1


def _give_back_core() -> None:
    """The caller's torch threads back once the last started function is taken."""
    global _cores_taken
    with _pool_lock:
        _cores_taken -= 1
        if _cores_taken == 0 and _threads_before > 1:
            torch.set_num_threads(_threads_before)


@contextlib.contextmanager
def deferred(fn: Callable[..., Any], *args: Any, parallel: bool = True) -> Iterator[Pending]:
    """``fn(*args)`` for the second thread, started by whoever knows that thread is idle
    (:meth:`Pending.start`: a solver, once its own work there is done), else run by
    :meth:`Pending.result` on the caller's thread: the same results either way. The block does
    not end before a started ``fn`` has, even when the body raises, so nothing ``fn`` touches is
    used by two windows at once.

    Yields:
        :class:`Pending`, whose ``result()`` gives ``fn``'s return value.
    """
    pending = Pending(fn, args, parallel)
    try:
        yield pending
    finally:
        pending._finish()


@contextlib.contextmanager
def alongside(fn: Callable[..., Any], *args: Any, parallel: bool = True) -> Iterator[Pending]:
    """Run ``fn(*args)`` on the process's second thread while the ``with`` body runs
    (:func:`deferred`, started at once).

    One second thread serves the process: calls from different threads queue for it.
    ``parallel=False`` — or a call from that thread itself — runs ``fn`` only when
    :meth:`Pending.result` is asked for, on the caller's thread: the same results, sequentially.

    Yields:
        :class:`Pending`, whose ``result()`` gives ``fn``'s return value.
    """
    with deferred(fn, *args, parallel=parallel) as pending:
        pending.start()
        yield pending


def _timed(fn: Callable[..., Any], args: tuple):
    """fn(*args) and the stages it timed, on the second thread (which has no recorder of its own)."""
    times = StageTimes()
    with times.recording():
        value = fn(*args)
    return value, times.seconds


@contextlib.contextmanager
def one_torch_thread() -> Iterator[None]:
    """The calling thread's torch ops on one thread inside the block; its count restored after.

    For results that must not depend on timing. The bits of a CPU matrix product can depend on
    how many threads share it (the edge head's, on an Intel Xeon: 2 of a 4 x 500 window's 20 667
    probabilities differ by one unit in the last place between one and two threads), and the
    caller's count depends on whether a function started on the second thread has been taken yet
    (:func:`_take_core`): a stream's scores then differed between runs of the same windows.
    """
    before = torch.get_num_threads()
    if before == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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
    per-thread set-up cannot later replace it with the process's count. Its id kept for placing it
    on a CPU from the caller's thread (no round trip through the queue)."""
    global _second_tid
    _second_tid = threading.get_native_id()
    torch.get_num_threads()
    torch.set_num_threads(1)
