"""Conversions between the ROS messages and the core types (no node, no executor needed).

- ``gcn_match_msgs/Keypoints`` <- :class:`gcn_match_ros.windowing.Frame`
  (:func:`frame_to_keypoints`: an rclpy message from :func:`gcn_match_ros.bags.codec.keypoints_fields`;
  the other way is :func:`gcn_match_ros.bags.codec.frame_from_keypoints_msg`, which reads rclpy
  and rosbags messages alike — one encoder, one decoder);
- a window's frames + a solver's :class:`~gcn_match_ros.problem.Result` ->
  ``gcn_match_msgs/MatchWindow`` (:func:`result_to_match_window`), checked by
  :func:`validate_match_window` before anything is published;
- ``MatchWindow`` -> numpy for consumers (:func:`match_window_to_arrays`, :func:`window_tracks`,
  :func:`pairwise_matches`, :func:`soft_pairwise_matches`).

Array fields are read with ``np.frombuffer`` (no copy, no per-element Python work) and
filled with ``array.array(typecode, ndarray.tobytes())``. Stamps stay integer nanoseconds
(:mod:`gcn_match_ros.stamps`). An inconsistent result raises :class:`MatchWindowError`
(a ``ValueError``) with a counter reason.
"""
from __future__ import annotations

import array
import dataclasses
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from builtin_interfaces.msg import Time
from gcn_match_msgs.msg import Keypoints, MatchWindow
from sensor_msgs.msg import CameraInfo

from ..bags.codec import camera_info_fields, keypoints_fields, message_array
from ..problem import Result
from ..rounding import relabel_tracks
from ..stamps import ns_to_sec_nanosec, stamp_to_ns
from ..windowing import Frame

__all__ = [
    "DENSE_MAX_KEYPOINTS", "MatchWindowError", "ns_to_time", "frame_to_keypoints",
    "result_to_match_window", "validate_match_window",
    "WindowArrays", "match_window_to_arrays", "window_tracks", "pairwise_matches",
    "soft_pairwise_matches",
]


#: A dense N×N score matrix is only attached up to this many keypoints (64 MiB of float32).
DENSE_MAX_KEYPOINTS = 4096


class MatchWindowError(ValueError):
    """A result or MatchWindow that would be inconsistent; ``reason`` is a short counter key."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


# ---------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------
_TYPECODES = {np.dtype(np.float32): "f", np.dtype(np.float64): "d", np.dtype(np.uint8): "B",
              np.dtype(np.int32): "i", np.dtype(np.uint32): "I", np.dtype(np.int64): "q"}


def _seq(a, dtype) -> array.array:
    """A numpy array as the ``array.array`` an rclpy sequence field takes without per-element checks."""
    a = np.ascontiguousarray(a, dtype)
    return array.array(_TYPECODES[a.dtype], a.tobytes())


def ns_to_time(ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time."""
    sec, nanosec = ns_to_sec_nanosec(ns)
    return Time(sec=sec, nanosec=nanosec)


# ---------------------------------------------------------------------------------------
# Frame -> Keypoints
# ---------------------------------------------------------------------------------------
def frame_to_keypoints(frame: Frame, camera_info: Optional[CameraInfo] = None) -> Keypoints:
    """A :class:`Frame` as an rclpy ``Keypoints`` message (fields by :func:`keypoints_fields`).

    Args:
        camera_info: a ``sensor_msgs/CameraInfo`` to attach as is (e.g. the camera's own, with
            distortion); default one from ``frame.K`` and ``frame.image_size``.

    Raises:
        ValueError: a binary frame whose descriptors are not 0/1.
    """
    msg = Keypoints()
    msg.header.stamp = ns_to_time(frame.stamp_ns)
    msg.header.frame_id = frame.frame_id or ""
    for name, value in keypoints_fields(frame).items():
        setattr(msg, name, _seq(value, value.dtype) if isinstance(value, np.ndarray) else value)
    if camera_info is not None:
        msg.camera_info = camera_info
    else:
        fields = camera_info_fields(frame.K, frame.image_size)
        msg.camera_info.header = msg.header
        for name, value in fields.items():
            # fixed-size arrays (k, r, p) take numpy float64, sequences (d) an array.array
            setattr(msg.camera_info, name, _seq(value, np.float64) if name == "d" else value)
    return msg


# ---------------------------------------------------------------------------------------
# Result -> MatchWindow
# ---------------------------------------------------------------------------------------
def result_to_match_window(frames: Sequence[Frame], result: Result, *, score_threshold: float = 0.0,
                           dense: bool = False, build_seconds: float = 0.0, solve_seconds: float = 0.0,
                           total_seconds: float = 0.0, latency_seconds: float = 0.0,
                           method: Optional[str] = None, frame_id: str = "",
                           landmark_ids: Optional[np.ndarray] = None,
                           landmark_ages: Optional[np.ndarray] = None) -> MatchWindow:
    """The MatchWindow of one solved window (views in ``frames`` order).

    Pairs with score > ``score_threshold`` go into the sparse COO fields. With ``dense`` and
    N <= :data:`DENSE_MAX_KEYPOINTS`, ``dense_scores`` holds the symmetric N×N matrix of all
    the result's pair scores (unthresholded) with 1 on the diagonal; above that size it stays
    empty. Track ids are renumbered 0..T-1 (keypoints alone in their track become -1).
    ``view_stamps`` are the frames' stamps, exactly; the header stamp is the newest of them.
    ``landmark_ids`` (N,) and ``landmark_ages`` (N,) seconds: the window's persistent landmarks
    (:func:`gcn_match_ros.stream.solve_window`), or None (the fields stay empty).

    Raises:
        MatchWindowError: the result does not fit the frames (never a wrong-shaped message).
    """
    if not frames:
        raise MatchWindowError("empty_window", "window has no frames")
    sizes = np.array([f.count for f in frames], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    n = int(offsets[-1])
    track = np.asarray(result.track, np.int64)
    if track.shape != (n,):
        raise MatchWindowError("bad_result", f"track: expected shape ({n},), got {track.shape}")
    rows = np.asarray(result.pair_rows, np.int64)
    cols = np.asarray(result.pair_cols, np.int64)
    scores = np.asarray(result.pair_scores, np.float32)
    if not (rows.shape == cols.shape == scores.shape and rows.ndim == 1):
        raise MatchWindowError("bad_result", f"pair arrays differ in shape: {rows.shape}, {cols.shape}, "
                                             f"{scores.shape}")
    if rows.size:
        if rows.min() < 0 or cols.max() >= n or np.any(rows >= cols):
            raise MatchWindowError("bad_result", f"pair indices must satisfy 0 <= row < col < {n}")
        if not np.all(np.isfinite(scores)):
            raise MatchWindowError("bad_result", "pair scores contain NaN or inf")
    view = np.repeat(np.arange(len(frames), dtype=np.int64), sizes)
    if rows.size and np.any(view[rows] == view[cols]):
        raise MatchWindowError("bad_result", "a pair joins two keypoints of one view")
    track = relabel_tracks(track)
    matched = track >= 0
    keys = track[matched] * len(frames) + view[matched]
    if keys.size != np.unique(keys).size:
        raise MatchWindowError("bad_result", "a track holds two keypoints of one view")
    scores = np.clip(scores, 0.0, 1.0)
    if (landmark_ids is None) != (landmark_ages is None):
        raise MatchWindowError("bad_result", "landmark_ids and landmark_ages go together")
    if landmark_ids is not None:
        landmark_ids = np.asarray(landmark_ids, np.int64)
        landmark_ages = np.asarray(landmark_ages, np.float32)
        if landmark_ids.shape != (n,) or landmark_ages.shape != (n,):
            raise MatchWindowError("bad_result", f"landmarks: expected ({n},) ids and ages, got "
                                                 f"{landmark_ids.shape}, {landmark_ages.shape}")

    msg = MatchWindow()
    msg.header.stamp = ns_to_time(max(f.stamp_ns for f in frames))
    msg.header.frame_id = frame_id
    msg.camera_ids = [f.camera_id for f in frames]
    msg.frame_ids = [f.frame_id or "" for f in frames]
    msg.view_stamps = [ns_to_time(f.stamp_ns) for f in frames]
    msg.view_offsets = _seq(offsets, np.uint32)
    keep = scores > score_threshold
    msg.pair_rows = _seq(rows[keep], np.uint32)
    msg.pair_cols = _seq(cols[keep], np.uint32)
    msg.pair_scores = _seq(scores[keep], np.float32)
    msg.score_threshold = float(score_threshold)
    if dense and n <= DENSE_MAX_KEYPOINTS:
        d = np.zeros((n, n), np.float32)
        d[rows, cols] = scores
        d[cols, rows] = scores
        np.fill_diagonal(d, 1.0)
        msg.dense_scores = _seq(d, np.float32)
    msg.track = _seq(track, np.int32)
    msg.track_count = int(track.max(initial=-1) + 1)
    msg.method = method if method is not None else result.method
    msg.build_seconds = float(build_seconds)
    msg.solve_seconds = float(solve_seconds)
    msg.total_seconds = float(total_seconds)
    msg.latency_seconds = float(latency_seconds)
    if landmark_ids is not None:
        msg.landmark_ids = _seq(landmark_ids, np.int64)
        msg.landmark_ages = _seq(np.where(landmark_ids >= 0, landmark_ages, -1.0), np.float32)
    return msg


def validate_match_window(msg: MatchWindow) -> None:
    """Check every size and index of a MatchWindow; raises :class:`MatchWindowError`."""
    v = len(msg.camera_ids)
    if v < 1:
        raise MatchWindowError("bad_window", "camera_ids is empty")
    if len(msg.frame_ids) != v or len(msg.view_stamps) != v:
        raise MatchWindowError("bad_window", f"frame_ids ({len(msg.frame_ids)}) and view_stamps "
                                             f"({len(msg.view_stamps)}) must have V={v} entries")
    offs = message_array(msg.view_offsets, np.uint32).astype(np.int64)
    if offs.size != v + 1 or offs[0] != 0 or np.any(np.diff(offs) < 0):
        raise MatchWindowError("bad_window", f"view_offsets must be V+1={v + 1} non-decreasing values "
                                             f"from 0, got {offs.tolist()[:10]}")
    n = int(offs[-1])
    track = message_array(msg.track, np.int32).astype(np.int64)
    if track.size != n:
        raise MatchWindowError("bad_window", f"track: {track.size} values, expected N={n}")
    t = int(msg.track_count)
    if track.size and (track.min() < -1 or track.max() >= t):
        raise MatchWindowError("bad_window", f"track ids must lie in [-1, {t})")
    view = np.repeat(np.arange(v, dtype=np.int64), np.diff(offs))
    m = track >= 0
    keys = track[m] * v + view[m]
    if keys.size != np.unique(keys).size:
        raise MatchWindowError("bad_window", "a track holds two keypoints of one view")
    rows = message_array(msg.pair_rows, np.uint32).astype(np.int64)
    cols = message_array(msg.pair_cols, np.uint32).astype(np.int64)
    scores = message_array(msg.pair_scores, np.float32)
    if not rows.size == cols.size == scores.size:
        raise MatchWindowError("bad_window", f"pair_rows/pair_cols/pair_scores lengths differ: "
                                             f"{rows.size}, {cols.size}, {scores.size}")
    if rows.size:
        if np.any(rows >= cols) or cols.max() >= n:
            raise MatchWindowError("bad_window", f"pairs must satisfy row < col < N={n}")
        if np.any(view[rows] == view[cols]):
            raise MatchWindowError("bad_window", "a pair joins two keypoints of one view")
        if not (np.all(np.isfinite(scores)) and scores.min() >= 0.0 and scores.max() <= 1.0):
            raise MatchWindowError("bad_window", "pair scores must lie in [0, 1]")
    nd = len(msg.dense_scores)
    if nd not in (0, n * n):
        raise MatchWindowError("bad_window", f"dense_scores: {nd} values, expected 0 or N*N={n * n}")
    nl, na = len(msg.landmark_ids), len(msg.landmark_ages)
    if nl != na or nl not in (0, n):
        raise MatchWindowError("bad_window", f"landmark_ids / landmark_ages: {nl} / {na} values, expected 0 or N={n}")
    if nl and message_array(msg.landmark_ids, np.int64).min() < -1:
        raise MatchWindowError("bad_window", "landmark ids must be >= -1")


# ---------------------------------------------------------------------------------------
# MatchWindow -> numpy (for consumers)
# ---------------------------------------------------------------------------------------
@dataclasses.dataclass
class WindowArrays:
    """A MatchWindow as numpy arrays.

    Shapes:
        camera_ids, frame_ids: V strings; view_stamps_ns: (V,) int64 stamps; stamp_ns: the newest.
        view_offsets: (V+1,) int64. view_index, local_index: (N,) int64 — the view of each
            global keypoint row and its index in that view's Keypoints message.
        track: (N,) int64 (-1 unmatched), track_count: T.
        pair_rows, pair_cols: (M,) int64 global rows; pair_scores: (M,) float32.
        dense_scores: (N, N) float32 or None.
        landmark_ids: (N,) int64 persistent landmark ids (-1: none), landmark_ages: (N,)
            float32 seconds; both None when the producer tracks no landmarks.
    """

    camera_ids: List[str]
    frame_ids: List[str]
    stamp_ns: int
    view_stamps_ns: np.ndarray
    view_offsets: np.ndarray
    view_index: np.ndarray
    local_index: np.ndarray
    track: np.ndarray
    track_count: int
    pair_rows: np.ndarray
    pair_cols: np.ndarray
    pair_scores: np.ndarray
    dense_scores: Optional[np.ndarray]
    method: str
    latency_seconds: float
    total_seconds: float
    landmark_ids: Optional[np.ndarray] = None
    landmark_ages: Optional[np.ndarray] = None

    @property
    def n_views(self) -> int:
        return len(self.camera_ids)

    @property
    def n_keypoints(self) -> int:
        return int(self.view_offsets[-1])


def match_window_to_arrays(msg: MatchWindow, validate: bool = True) -> WindowArrays:
    """Numpy view of a MatchWindow (validated first unless ``validate=False``)."""
    if validate:
        validate_match_window(msg)
    offs = message_array(msg.view_offsets, np.uint32).astype(np.int64)
    sizes = np.diff(offs)
    v = sizes.size
    view_index = np.repeat(np.arange(v, dtype=np.int64), sizes)
    n = int(offs[-1])
    local = np.arange(n, dtype=np.int64) - offs[:-1][view_index] if n else np.zeros(0, np.int64)
    dense = message_array(msg.dense_scores, np.float32)
    return WindowArrays(
        camera_ids=list(msg.camera_ids), frame_ids=list(msg.frame_ids),
        stamp_ns=stamp_to_ns(msg.header.stamp),
        view_stamps_ns=np.array([stamp_to_ns(s) for s in msg.view_stamps], np.int64),
        view_offsets=offs, view_index=view_index, local_index=local,
        track=message_array(msg.track, np.int32).astype(np.int64), track_count=int(msg.track_count),
        pair_rows=message_array(msg.pair_rows, np.uint32).astype(np.int64),
        pair_cols=message_array(msg.pair_cols, np.uint32).astype(np.int64),
        pair_scores=message_array(msg.pair_scores, np.float32).copy(),
        dense_scores=dense.reshape(n, n).copy() if dense.size and dense.size == n * n else None,
        method=msg.method, latency_seconds=float(msg.latency_seconds), total_seconds=float(msg.total_seconds),
        landmark_ids=message_array(msg.landmark_ids, np.int64).copy() if len(msg.landmark_ids) else None,
        landmark_ages=message_array(msg.landmark_ages, np.float32).copy() if len(msg.landmark_ages) else None)


def _as_arrays(window) -> WindowArrays:
    return window if isinstance(window, WindowArrays) else match_window_to_arrays(window)


def window_tracks(window) -> List[List[Tuple[int, int]]]:
    """Tracks as lists of (view, keypoint index in that view), track id order.

    ``window``: a MatchWindow or :class:`WindowArrays`.
    """
    w = _as_arrays(window)
    idx = np.flatnonzero(w.track >= 0)
    order = idx[np.argsort(w.track[idx], kind="stable")]
    t = w.track[order]
    bounds = np.flatnonzero(np.r_[True, t[1:] != t[:-1], True]) if t.size else np.zeros(1, np.int64)
    views, local = w.view_index[order].tolist(), w.local_index[order].tolist()
    return [list(zip(views[s:e], local[s:e])) for s, e in zip(bounds[:-1], bounds[1:])]


def pairwise_matches(window) -> Dict[Tuple[int, int], np.ndarray]:
    """Hard matches implied by the tracks, per view pair (i < j): (K, 2) int64 arrays of
    (keypoint index in view i, keypoint index in view j)."""
    w = _as_arrays(window)
    v = w.n_views
    out: Dict[Tuple[int, int], np.ndarray] = {}
    if w.track_count == 0:
        return out
    # (T, V) table of the global row of each track in each view, -1 where absent.
    table = np.full((w.track_count, v), -1, np.int64)
    m = w.track >= 0
    table[w.track[m], w.view_index[m]] = np.flatnonzero(m)
    for i in range(v):
        for j in range(i + 1, v):
            both = (table[:, i] >= 0) & (table[:, j] >= 0)
            if both.any():
                out[(i, j)] = np.stack([w.local_index[table[both, i]], w.local_index[table[both, j]]], axis=1)
    return out


def soft_pairwise_matches(window, min_score: float = 0.0) -> Dict[Tuple[int, int], Tuple[np.ndarray, np.ndarray]]:
    """Listed soft matches per view pair (i < j): ((K, 2) int64 local indices, (K,) scores),
    only scores > ``min_score``."""
    w = _as_arrays(window)
    keep = w.pair_scores > min_score
    r, c, s = w.pair_rows[keep], w.pair_cols[keep], w.pair_scores[keep]
    vi, vj = w.view_index[r], w.view_index[c]
    out = {}
    if r.size == 0:
        return out
    key = vi * w.n_views + vj
    order = np.argsort(key, kind="stable")
    key = key[order]
    bounds = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    for s0, e0 in zip(bounds[:-1], bounds[1:]):
        sel = order[s0:e0]
        i, j = divmod(int(key[s0]), w.n_views)
        out[(i, j)] = (np.stack([w.local_index[r[sel]], w.local_index[c[sel]]], axis=1), s[sel])
    return out
