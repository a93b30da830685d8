"""Compiled sorting of small buckets, shared by the candidate edges and the network's normalised
adjacency.

Each sorts entries first by one key with a counting sort (bucket boundaries ``start``), then each
bucket, a few dozen entries at most, by a second key: :func:`sort_buckets` is that second step.
:func:`bucket_starts` is the first step's boundaries, :func:`bucket_order` the first step where only
the order is needed.
"""
from __future__ import annotations

import numba
import numpy as np

__all__ = ["bucket_starts", "bucket_order", "sort_buckets"]


@numba.njit(cache=True, nogil=True)
def bucket_starts(keys, n_buckets):
    """The boundaries of the buckets a counting sort by ``keys`` fills: bucket v holds positions
    ``start[v]:start[v + 1]``. A caller that scatters its own payload fills them itself (from a copy
    of ``start[:-1]``): a third faster than gathering by :func:`bucket_order`'s order.

    Shapes: keys (M,) int64 in [0, n_buckets) -> start (n_buckets + 1,) int64.
    """
    start = np.zeros(n_buckets + 1, np.int64)
    for m in range(keys.shape[0]):
        start[keys[m] + 1] += 1
    for v in range(n_buckets):
        start[v + 1] += start[v]
    return start


@numba.njit(cache=True, nogil=True)
def bucket_order(keys, n_buckets):
    """The positions of ``keys`` grouped by key, ascending, each key's in their order (a stable
    counting sort), and the buckets' boundaries (:func:`bucket_starts`).

    Shapes: keys (M,) int64 in [0, n_buckets) -> start (n_buckets + 1,) int64, order (M,) int64:
    ``keys[order[start[v]:start[v + 1]]] == v``.
    """
    start = bucket_starts(keys, n_buckets)
    fill = start[:-1].copy()
    order = np.empty(keys.shape[0], np.int64)
    for m in range(keys.shape[0]):
        order[fill[keys[m]]] = m
        fill[keys[m]] += 1
    return start, order


@numba.njit(cache=True, nogil=True)
def sort_buckets(start, keys, carried):
    """Sort every bucket ``keys[start[v]:start[v + 1]]`` ascending in place, moving ``carried``
    along: a stable insertion sort (buckets of a few dozen entries; an already sorted one costs
    one pass).

    Shapes: start (B + 1,) int64 non-decreasing; keys, carried (start[B],), any dtypes.
    """
    for v in range(start.shape[0] - 1):
        lo, hi = start[v], start[v + 1]
        for t in range(lo + 1, hi):
            key, value = keys[t], carried[t]
            u = t
            while u > lo and keys[u - 1] > key:
                keys[u], carried[u] = keys[u - 1], carried[u - 1]
                u -= 1
            keys[u], carried[u] = key, value
