"""Tests of gcn_match_ros.libc: the C library's functions found, declared and missing."""
import ctypes
import os
import sys

import pytest

from gcn_match_ros import libc
from gcn_match_ros.libc import c_function


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's sched_getcpu")
def test_a_function_is_found_with_its_signature():
    """sched_getcpu answers the CPU this thread runs on, one of those it may run on."""
    sched_getcpu = c_function("sched_getcpu")
    assert sched_getcpu is not None and sched_getcpu.restype is ctypes.c_int
    assert sched_getcpu() in os.sched_getaffinity(0)


def test_each_caller_declares_its_own_signature():
    """Two callers of one function get function objects of their own: declaring one does not
    change the other's."""
    first = c_function("abs", (ctypes.c_int,), ctypes.c_int)
    if first is None:
        pytest.skip("no C library reachable from this process")
    second = c_function("abs", (ctypes.c_long,), ctypes.c_long)
    assert first is not second
    assert first.argtypes == [ctypes.c_int] and first.restype is ctypes.c_int
    assert second.argtypes == [ctypes.c_long] and second.restype is ctypes.c_long
    assert first(-7) == 7


def test_missing_functions_and_libraries_are_none(monkeypatch):
    """A function the library lacks, or no library at all, is None for the caller to do without."""
    assert c_function("gcn_match_ros_no_such_function") is None
    libc._process_library.cache_clear()

    def unavailable(name):
        raise OSError("no C library")

    monkeypatch.setattr(ctypes, "CDLL", unavailable)
    try:
        assert c_function("abs") is None
    finally:
        libc._process_library.cache_clear()
