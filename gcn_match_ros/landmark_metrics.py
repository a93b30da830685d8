"""How well landmark ids persist, against true point ids over a sequence of windows.

Per window: ``ids`` (N,) the landmark id given to each keypoint (-1: none) and ``truth`` (N,)
its true point id (-1: a distractor). A landmark's point in a window is the true point most of
its keypoints show (a landmark on distractors only has none).

- id precision: of the landmark continuations (a landmark present in two consecutive windows),
  the share whose point is the same in both;
- id switches per 100 true point-windows: a true point seen with an id in two consecutive
  windows whose (majority) id changed, per 100 windows in which a true point has an id;
- fragmentation: distinct ids per true point that got any id (1 = never re-identified);
- lifetime: mean windows from a landmark's first to its last window, against the mean span of
  the true points' visibility (first to last window seen, windows with an id only).
"""
from __future__ import annotations

import collections
from typing import Dict, Sequence

import numpy as np

__all__ = ["landmark_scores", "true_points"]


def true_points(labels, n: int) -> np.ndarray:
    """The ``truth`` of one window from a bag's scene-global labels (``bags.contents``): the
    point id of each keypoint, -1 for none and for unlabelled (-2) ones, all -1 without labels.

    Shapes: labels (N,) or None -> (N,) int64 (``n`` = N).
    """
    if labels is None:
        return np.full(n, -1, np.int64)
    return np.where(np.asarray(labels) >= 0, labels, -1).astype(np.int64)


def _majority(keys: np.ndarray, values: np.ndarray) -> Dict[int, int]:
    """key -> its most frequent value (ties: the smallest), over pairs with key, value >= 0."""
    out: Dict[int, collections.Counter] = collections.defaultdict(collections.Counter)
    for k, v in zip(keys.tolist(), values.tolist()):
        if k >= 0 and v >= 0:
            out[k][v] += 1
    return {k: min(c, key=lambda v: (-c[v], v)) for k, c in out.items()}


def landmark_scores(ids: Sequence[np.ndarray], truth: Sequence[np.ndarray]) -> Dict[str, float]:
    """The metrics of the module docstring over one sequence (windows in order)."""
    point_of = [_majority(i, t) for i, t in zip(ids, truth)]   # per window: landmark -> point
    id_of = [_majority(t, i) for i, t in zip(ids, truth)]      # per window: point -> landmark
    continuations = same = 0
    for a, b in zip(point_of[:-1], point_of[1:]):
        for lm in a.keys() & b.keys():
            continuations += 1
            same += a[lm] == b[lm]
    switches = point_windows = 0
    for a, b in zip(id_of[:-1], id_of[1:]):
        for p in a.keys() & b.keys():
            switches += a[p] != b[p]
    point_windows = sum(len(m) for m in id_of)
    ids_per_point: Dict[int, set] = collections.defaultdict(set)
    span_point: Dict[int, list] = {}
    for w, m in enumerate(id_of):
        for p, lm in m.items():
            ids_per_point[p].add(lm)
            span_point.setdefault(p, [w, w])[1] = w
    span_landmark: Dict[int, list] = {}
    for w, i in enumerate(ids):
        for lm in np.unique(i[i >= 0]).tolist():
            span_landmark.setdefault(lm, [w, w])[1] = w
    return {
        "id_precision": same / continuations if continuations else float("nan"),
        "switches_per_100": 100.0 * switches / point_windows if point_windows else float("nan"),
        "fragmentation": float(np.mean([len(s) for s in ids_per_point.values()])) if ids_per_point else float("nan"),
        "lifetime": float(np.mean([e - s + 1 for s, e in span_landmark.values()])) if span_landmark else float("nan"),
        "true_span": float(np.mean([e - s + 1 for s, e in span_point.values()])) if span_point else float("nan"),
        "landmarks": float(len(span_landmark)),
        "continuations": float(continuations),
    }
