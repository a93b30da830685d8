"""Functions of the process's C library that Python has no binding for, found in one place.

The allocator setting (``mallopt``, :mod:`gcn_match_ros.allocator`), the CPU a thread runs on
(``sched_getcpu``, :mod:`gcn_match_ros.threads`) and the heap statistics of the memory benchmark
(``mallinfo2``) come from glibc. Elsewhere (musl, macOS, Windows) a function may be missing: the
caller then gets None and does without it.
"""
from __future__ import annotations

import ctypes
import functools
from typing import Any, Callable, Optional, Sequence

__all__ = ["c_function"]


@functools.lru_cache(maxsize=1)
def _process_library() -> Optional[ctypes.CDLL]:
    """The C library the process is linked with (its own symbols), loaded once; None where it
    cannot be opened so."""
    try:
        return ctypes.CDLL(None)
    except OSError:
        return None


def c_function(name: str, argtypes: Sequence[Any] = (), restype: Any = ctypes.c_int) -> Optional[Callable]:
    """The C library's function ``name`` with the given signature, or None where it has none.

    Each call gives a function object of its own, so two callers may declare one function
    differently without changing each other's.
    """
    library = _process_library()
    if library is None:
        return None
    try:
        function = library[name]
    except AttributeError:
        return None
    function.argtypes, function.restype = list(argtypes), restype
    return function
