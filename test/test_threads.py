"""Tests of gcn_match_ros.threads: numpy's BLAS on one thread, torch's pool untouched; work
beside the caller on a second thread; the two threads placed on CPUs (pinned, kept apart per window)."""
import concurrent.futures
import contextlib
import functools
import gc
import os
import threading
import time
import weakref

import numpy as np
import pytest
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from gcn_match_ros.threads import (SharedTasks, alongside, deferred, kept_apart, one_torch_thread,
                                   pinned_solve_threads, single_blas_thread, solve_cpus)
from gcn_match_ros.timing import StageTimes, stage

from conftest import PROCESS_CPUS, needs_two_cpus, second_thread_cpus


def test_single_blas_thread_limits_numpys_blas_and_leaves_torch_alone():
    torch_threads = torch.get_num_threads()
    original = threadpool_limits(limits=None)  # restores whatever this process had afterwards
    try:
        single_blas_thread()
        blas = [i for i in threadpool_info() if i["user_api"] == "blas"]
        assert blas and all(i["num_threads"] == 1 for i in blas)
        a = np.random.default_rng(0).normal(size=(64, 64))
        np.testing.assert_allclose(a @ np.linalg.inv(a), np.eye(64), atol=1e-8)  # still numpy's BLAS
        assert torch.get_num_threads() == torch_threads
    finally:
        original.restore_original_limits()


def test_torch_runs_on_one_thread_on_the_second_thread_and_other_threads_keep_their_count():
    threads = torch.get_num_threads()

    def torch_work():
        torch.relu(torch.randn(1 << 16))  # an op torch parallelises
        return torch.get_num_threads()

    with alongside(torch_work) as pending:
        assert torch.get_num_threads() == max(1, threads - 1)  # a core left for the second thread
        assert pending.result() == 1
        assert torch.get_num_threads() == threads  # given back with the result
    assert torch.get_num_threads() == threads
    with alongside(torch_work) as pending:
        pass  # never asked for: given back when the block ends
    assert torch.get_num_threads() == threads
    with pytest.raises(RuntimeError, match="body"):
        with alongside(torch_work):
            raise RuntimeError("body")
    assert torch.get_num_threads() == threads  # and when the body raises
    later = []
    t = threading.Thread(target=lambda: later.append(torch.get_num_threads()))
    t.start()
    t.join()
    assert later == [threads]  # a thread started afterwards takes the process's count


def test_alongside_runs_on_a_second_thread_and_adds_its_stages_to_the_callers():
    started = threading.Event()

    def work(x):
        started.set()
        with stage("beside"):
            return x + 1, threading.current_thread()

    times = StageTimes()
    with times.recording():
        with alongside(work, 41) as pending:
            assert started.wait(5)  # it runs before anyone asks for it
            with stage("here"):
                pass
            value, thread = pending.result()
    assert value == 42 and thread is not threading.current_thread()
    assert set(times.seconds) == {"beside", "here"}


def test_alongside_without_parallel_runs_on_asking_on_the_callers_thread():
    calls = []
    with alongside(lambda: calls.append(threading.current_thread()) or "done", parallel=False) as pending:
        assert calls == []
        assert pending.result() == "done" and pending.result() == "done"
    assert calls == [threading.current_thread()]


def test_alongside_raises_the_functions_error_at_result():
    def fails():
        raise ValueError("bad window")

    threads = torch.get_num_threads()
    with alongside(fails) as pending:
        with pytest.raises(ValueError, match="bad window"):
            pending.result()
        assert torch.get_num_threads() == threads  # the caller's core given back all the same


@pytest.mark.parametrize("started", ["alongside", "deferred, then start()"])
def test_the_block_waits_for_the_function_even_when_the_body_raises(started):
    finished = threading.Event()
    release = threading.Event()

    def slow():
        release.wait(5)
        finished.set()

    @contextlib.contextmanager
    def running(fn):
        if started == "alongside":
            with alongside(fn) as pending:
                yield pending
        else:
            with deferred(fn) as pending:
                pending.start()
                yield pending

    threads = torch.get_num_threads()
    with pytest.raises(RuntimeError, match="body"):
        with running(slow):
            release.set()
            raise RuntimeError("body")
    assert finished.is_set()  # e.g. a stream's rig memory is free for the next window
    assert torch.get_num_threads() == threads


def test_alongside_called_from_the_second_thread_runs_inline_instead_of_waiting_for_itself():
    def outer():
        with alongside(lambda: threading.current_thread()) as inner:
            return inner.result() is threading.current_thread()

    with alongside(outer) as pending:
        assert pending.result() is True


def test_deferred_runs_on_the_second_thread_once_started_else_on_the_caller_at_result():
    threads = torch.get_num_threads()
    with deferred(threading.current_thread) as never_started:
        assert torch.get_num_threads() == threads  # nothing taken before start()
    assert never_started.result() is threading.current_thread()
    with deferred(lambda: (threading.current_thread(), torch.get_num_threads())) as pending:
        pending.start()
        pending.start()  # once
        assert torch.get_num_threads() == max(1, threads - 1)
        thread, its_threads = pending.result()
        assert torch.get_num_threads() == threads
    assert thread is not threading.current_thread() and its_threads == 1
    with deferred(threading.current_thread, parallel=False) as sequential:
        sequential.start()  # parallel=False: nothing started
        assert sequential.result() is threading.current_thread()


def test_the_callers_core_comes_back_when_the_last_started_function_is_taken():
    """Functions queued one after another on the second thread (a solver's candidate edges, then
    its caller's work beside the solve) take one core between them, given back after the last."""
    threads = torch.get_num_threads()
    with alongside(lambda: 1) as first:
        with deferred(lambda: 2) as second:
            second.start()
            assert torch.get_num_threads() == max(1, threads - 1)
            assert first.result() == 1
            assert torch.get_num_threads() == max(1, threads - 1)  # the second still runs or waits
            assert second.result() == 2
            assert torch.get_num_threads() == threads


def test_a_start_not_yet_begun_can_be_withdrawn_and_then_runs_on_the_caller():
    threads = torch.get_num_threads()
    release = threading.Event()
    with alongside(release.wait, 5):  # the second thread busy
        with deferred(threading.current_thread) as queued:
            queued.start()
            assert queued.withdraw()  # still queued behind the first
            assert torch.get_num_threads() == max(1, threads - 1)  # the first still holds its core
            release.set()
            assert queued.result() is threading.current_thread()
            assert not queued.withdraw()  # nothing started
    assert torch.get_num_threads() == threads
    with deferred(threading.current_thread) as begun:
        begun.start()
        thread = begun.result()
        assert not begun.withdraw()  # done already
    assert thread is not threading.current_thread()


def test_one_torch_thread_gives_the_callers_count_back_also_when_the_body_raises():
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with one_torch_thread():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        with pytest.raises(RuntimeError), one_torch_thread():
            raise RuntimeError("boom")
        assert torch.get_num_threads() == 2
        torch.set_num_threads(1)
        with one_torch_thread():
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_shared_tasks_run_each_task_once_whoever_takes_it():
    """Two threads helping: every task runs once, results come back in the tasks' order, and
    they are taken in the order given."""
    ran, lock = [], threading.Lock()

    def task(k):
        with lock:
            ran.append(k)
        time.sleep(0.001)
        return k * k

    tasks = SharedTasks([functools.partial(task, k) for k in range(20)], order=range(19, -1, -1))
    helper = threading.Thread(target=tasks.help)
    helper.start()
    assert tasks.results() == [k * k for k in range(20)]
    helper.join()
    assert sorted(ran) == list(range(20)) and len(tasks) == 20
    ran.clear()  # one thread: taken in the given order
    assert SharedTasks([functools.partial(task, k) for k in range(4)], order=[2, 0, 3, 1]).results() == [0, 1, 4, 9]
    assert ran == [2, 0, 3, 1]
    assert SharedTasks([]).results() == []


def test_shared_tasks_let_go_of_a_task_once_taken_so_an_owner_of_its_tasks_is_freed_without_the_cyclic_collector():
    """A task that is its owner's bound method (as a window's candidate job hands out its view
    pairs) would close a cycle owner -> tasks -> method -> owner: the owner, and every array it
    holds, would then wait for the cyclic collector's rare full pass."""

    class Owner:
        def __init__(self):
            self.tasks = SharedTasks([self.work, self.work])

        def work(self):
            return 1

    gc.collect()
    gc.disable()
    try:
        owner = Owner()
        assert owner.tasks.results() == [1, 1]
        freed = weakref.ref(owner)
        del owner
        assert freed() is None  # by reference counting alone
    finally:
        gc.enable()


def test_shared_tasks_hand_the_first_error_to_the_caller_and_take_nothing_after_it():
    ran = []

    def task(k):
        ran.append(k)
        if k == 1:
            raise RuntimeError("task 1")
        return k

    tasks = SharedTasks([functools.partial(task, k) for k in range(5)])
    with pytest.raises(RuntimeError, match="task 1"):
        tasks.results()
    assert ran == [0, 1]
    with pytest.raises(ValueError, match="each of the 2 task positions once"):
        SharedTasks([int, int], order=[0, 0])


@needs_two_cpus
def test_solve_cpus_are_the_given_one_and_the_next_allowed_wrapping_around():
    assert solve_cpus(PROCESS_CPUS[0]) == (PROCESS_CPUS[0], PROCESS_CPUS[1])
    assert solve_cpus(PROCESS_CPUS[-1]) == (PROCESS_CPUS[-1], PROCESS_CPUS[0])
    with pytest.raises(ValueError, match="not one this process may use"):
        solve_cpus(max(PROCESS_CPUS) + 1)


@needs_two_cpus
def test_pinned_solve_threads_put_the_caller_and_the_second_thread_on_a_cpu_each_and_give_them_back():
    """Entered by a thread that solves (the node's worker), as the node does."""
    torch_threads = torch.get_num_threads()
    second_before = second_thread_cpus()
    seen = {}

    def worker():
        before = os.sched_getaffinity(0)
        with pinned_solve_threads(PROCESS_CPUS[1]) as cpus:
            seen["cpus"] = cpus
            seen["mine"] = os.sched_getaffinity(0)
            seen["torch"] = torch.get_num_threads()
            with alongside(lambda: os.sched_getaffinity(0)) as pending:  # the work beside runs there
                seen["beside"] = pending.result()
        seen["mine after"] = os.sched_getaffinity(0) == before

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    first, second = seen["cpus"]
    assert (first, second) == solve_cpus(PROCESS_CPUS[1])
    assert seen["mine"] == {first} and seen["beside"] == {second} and seen["torch"] == 1
    assert seen["mine after"] and torch.get_num_threads() == torch_threads
    assert second_thread_cpus() == second_before
    assert os.sched_getaffinity(0) == set(PROCESS_CPUS)  # other threads stay where they were
    with pytest.raises(ValueError, match="not one this process may use"):
        with pinned_solve_threads(max(PROCESS_CPUS) + 1):
            pass


def _in_thread(fn):
    """fn() on a new thread (a solving thread of its own, as the node's worker): its value, or its
    exception raised here."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=1) as pool:
        return pool.submit(fn).result()


@needs_two_cpus
def test_kept_apart_keeps_the_caller_on_its_cpu_and_the_second_thread_on_the_next_then_gives_both_back():
    torch_threads, second_before = torch.get_num_threads(), second_thread_cpus()

    def solve():
        before = os.sched_getaffinity(0)
        with kept_apart():
            mine, torch_inside = os.sched_getaffinity(0), torch.get_num_threads()
            with alongside(lambda: os.sched_getaffinity(0)) as pending:  # the work beside runs there
                beside = pending.result()
            with kept_apart():  # nested (a solve inside a stream's window): already placed
                nested = os.sched_getaffinity(0), second_thread_cpus()
            still = os.sched_getaffinity(0), second_thread_cpus()
        return before, mine, torch_inside, beside, nested, still, os.sched_getaffinity(0)

    before, mine, torch_inside, beside, nested, still, after = _in_thread(solve)
    assert len(mine) == 1 and torch_inside == 1
    (cpu,) = mine
    assert beside == {solve_cpus(cpu)[1]} and beside != mine
    assert nested == still == (mine, beside)  # the inner block neither placed nor gave back
    assert after == before and second_thread_cpus() == second_before and torch.get_num_threads() == torch_threads


@needs_two_cpus
def test_kept_apart_places_nothing_when_disabled_or_when_the_caller_is_already_on_one_cpu():
    second_before = second_thread_cpus()

    def disabled():
        with kept_apart(False):
            return os.sched_getaffinity(0), second_thread_cpus(), torch.get_num_threads()

    assert _in_thread(disabled) == (set(PROCESS_CPUS), second_before, torch.get_num_threads())

    def pinned():  # the node's cpu_affinity: fixed CPUs for the worker's life
        with pinned_solve_threads(PROCESS_CPUS[1]) as (first, second):
            with kept_apart():
                inside = os.sched_getaffinity(0), second_thread_cpus()
            return (first, second), inside, (os.sched_getaffinity(0), second_thread_cpus())

    (first, second), inside, after = _in_thread(pinned)
    assert inside == after == ({first}, {second})
    assert second_thread_cpus() == second_before


@needs_two_cpus
def test_one_thread_places_the_second_thread_at_a_time():
    """The second thread serves the whole process: a thread's block that found it placed by
    another's places nothing (kept_apart) or says why (pinned_solve_threads), so that each block
    gives back what it found."""
    second_before = second_thread_cpus()
    placed, release = threading.Event(), threading.Event()

    def holder():
        with pinned_solve_threads(PROCESS_CPUS[0]):
            placed.set()
            release.wait(10)

    t = threading.Thread(target=holder)
    t.start()
    try:
        assert placed.wait(10)
        held = second_thread_cpus()

        def other():
            with kept_apart():
                return os.sched_getaffinity(0), second_thread_cpus()

        assert _in_thread(other) == (set(PROCESS_CPUS), held)
        with pytest.raises(ValueError, match="placed for another thread's solves"):
            with pinned_solve_threads(PROCESS_CPUS[1]):
                pass
    finally:
        release.set()
        t.join()
    assert second_thread_cpus() == second_before
