"""The latest messages of each camera by stamp, and a window's keypoints found in them.

Consumers of ``MatchWindow`` (the visualiser, the mapping node) need each view's keypoint
coordinates, which travel in the ``Keypoints`` messages the window names by camera and exact
stamp. :class:`StampBuffer` keeps the last few messages of every camera; :func:`window_frames`
finds a window's frames there and cuts them to the keypoints the matcher kept
(:func:`gcn_match_ros.windowing.trim_frame`, the one rule); :func:`decoded_window` unpacks a
window, counting and logging a malformed one.
"""
from __future__ import annotations

import collections
from typing import Deque, Dict, List, Optional, Sequence, Tuple

from ..bags.codec import frame_from_keypoints_msg
from ..stamps import stamp_to_ns
from ..windowing import Frame, FrameError, trim_frame
from .conversions import MatchWindowError, WindowArrays, match_window_to_arrays

__all__ = ["StampBuffer", "decoded_window", "window_frames"]


class StampBuffer:
    """The last ``depth`` messages (with a ``header``) of every camera, found by exact stamp."""

    def __init__(self, cameras: Sequence[str], depth: int = 30) -> None:
        self._by_camera: Dict[str, Deque[Tuple[int, object]]] = {
            c: collections.deque(maxlen=max(int(depth), 1)) for c in cameras}

    def add(self, camera: str, msg) -> None:
        self._by_camera[camera].append((stamp_to_ns(msg.header.stamp), msg))

    def find(self, camera: str, stamp_ns: int):
        """The message of ``camera`` stamped ``stamp_ns``, or None."""
        return next((m for s, m in reversed(self._by_camera.get(camera, ())) if s == stamp_ns), None)


def window_frames(window: WindowArrays, keypoints: StampBuffer) -> Tuple[Optional[List[Frame]], str]:
    """The window's frames cut to the keypoints the matcher kept, or (None, why not)."""
    frames = []
    for v, (cam, stamp) in enumerate(zip(window.camera_ids, window.view_stamps_ns.tolist())):
        msg = keypoints.find(cam, stamp)
        if msg is None:
            return None, f"no keypoints of {cam} at {stamp}"
        try:
            frame = frame_from_keypoints_msg(msg, camera_id=cam)
        except FrameError as exc:
            return None, str(exc)
        n_view = int(window.view_offsets[v + 1] - window.view_offsets[v])
        if frame.count < n_view:
            return None, f"{cam}: the window has {n_view} keypoints, its message {frame.count}"
        frames.append(trim_frame(frame, n_view))
    return frames, ""


def decoded_window(msg, counts: collections.Counter, logger, throttle_s: float) -> Optional[WindowArrays]:
    """The arrays of a ``MatchWindow``, or None for a malformed one, counted in
    ``counts["invalid windows"]`` and logged as a warning at most every ``throttle_s``."""
    try:
        return match_window_to_arrays(msg)
    except MatchWindowError as exc:
        counts["invalid windows"] += 1
        logger.warning(f"skipped an invalid window: {exc}", throttle_duration_sec=throttle_s)
        return None
