"""CPU threads of a process that solves windows: numpy's BLAS runs on one thread.

torch runs the network on its own thread pool (one thread per core). numpy's OpenBLAS keeps a
second pool of as many threads for the matrix products of the rest of a window (descriptor
products of the landmarks, two-view fits). On a 2-core robot computer both pools' threads spin
while they wait and take the cores from each other: a 4 x 500 window of the matcher node's path
took 134 ms with numpy's default and 66 ms with one BLAS thread (same outputs). The entry points
that solve (the matcher node, ``gcn-match``) call :func:`single_blas_thread` once at start-up.
"""
from __future__ import annotations

from threadpoolctl import threadpool_limits

__all__ = ["single_blas_thread"]


def single_blas_thread() -> None:
    """Limit every BLAS library loaded in this process (numpy's OpenBLAS) to one thread, for
    the rest of the process; torch's own pool is left as it is."""
    threadpool_limits(limits=1, user_api="blas")
