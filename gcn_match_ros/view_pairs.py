"""Pairs of keypoints grouped by the pair of views they join.

Every per-view-pair rule (a two-view model's check, the ratio along its epipolar line, the
neighbourhood rule) takes a window's pairs one view pair at a time. Selecting them with a mask
per view pair reads all M pairs once for each of a window's view pairs: 45 masks over ~10^5
pairs at 10 x 1000 took 60 ms; one sort groups them all.
"""
from __future__ import annotations

from typing import Dict, Tuple

import numpy as np

__all__ = ["by_view_pair", "in_view_order"]


def by_view_pair(view_a: np.ndarray, view_b: np.ndarray) -> Dict[Tuple[int, int], np.ndarray]:
    """The indices of the pairs of each view pair present, ascending (as ``np.flatnonzero`` of
    the view pair's mask gives them), keyed by (view_a, view_b) in ascending key order.

    Shapes: view_a, view_b (M,) non-negative ints -> {(a, b): (m_ab,) int64}.
    """
    view_a, view_b = np.asarray(view_a, np.int64), np.asarray(view_b, np.int64)
    if view_a.size == 0:
        return {}
    width = int(max(view_a.max(), view_b.max())) + 1
    key = view_a * width + view_b
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    ends = np.r_[starts[1:], key.size]
    return {(int(k // width), int(k % width)): order[s:e] for k, s, e in zip(sorted_key[starts], starts, ends)}


def in_view_order(view_index: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> Tuple[np.ndarray, ...]:
    """Pairs with each one's keypoint of the lower view first, and their views.

    Shapes: view_index (N,); rows, cols (M,) keypoints of different views -> rows, cols, view of
    rows, view of cols (M,) int64.
    """
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    va, vb = view_index[rows], view_index[cols]
    swap = va > vb
    return np.where(swap, cols, rows), np.where(swap, rows, cols), np.minimum(va, vb), np.maximum(va, vb)
