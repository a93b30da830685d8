"""match_consumer: how a downstream node (mapping, SLAM, calibration) uses MatchWindow.

Copy this file as the start of your own node. It subscribes ``matches`` (relative: remap it
to the matcher's output) and turns every window into

- **tracks**: one list per scene point of ``(view, keypoint index)`` — the keypoint index
  is the row in that view's ``Keypoints`` message (camera ``window.camera_ids[view]``,
  stamp ``window.view_stamps[view]``, ns in ``WindowArrays.view_stamps_ns``); tracks are cycle-consistent (at most one keypoint
  per view), so they can go straight into triangulation / bundle adjustment;
- **pairwise matches** per view pair (i, j): a (K, 2) array of keypoint indices in view i
  and view j (from the tracks), and the soft scores of the listed pairs if you want to
  apply your own threshold.

Everything is numpy on the message buffers (``gcn_match_ros.ros.conversions``), no
per-element Python work. Run::

    python -m gcn_match_ros.ros.example_consumer --ros-args -r matches:=/matcher_node/matches
"""
from __future__ import annotations

import collections
import sys

import numpy as np
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from gcn_match_msgs.msg import MatchWindow

from ..stamps import ns_to_seconds
from .conversions import (MatchWindowError, match_window_to_arrays, pairwise_matches, soft_pairwise_matches,
                          window_tracks)
from .spin import run_node

__all__ = ["MatchConsumer", "summarize", "main"]


def summarize(msg: MatchWindow, min_score: float = 0.5) -> dict:
    """Tracks and pairwise matches of one window, plus a one-line summary.

    Returns:
        dict with ``arrays`` (:class:`~gcn_match_ros.ros.conversions.WindowArrays`),
        ``tracks`` (list of lists of (view, keypoint index)), ``pairs`` ({(i, j): (K, 2)}),
        ``soft`` ({(i, j): ((K, 2), (K,) scores)} with score > ``min_score``) and ``text``.
    Raises:
        MatchWindowError: a malformed message.
    """
    w = match_window_to_arrays(msg)  # validates sizes and indices first
    tracks = window_tracks(w)
    pairs = pairwise_matches(w)
    soft = soft_pairwise_matches(w, min_score=min_score)
    lengths = collections.Counter(len(t) for t in tracks)
    per_pair = ", ".join(f"{w.camera_ids[i]}-{w.camera_ids[j]}: {len(m)}" for (i, j), m in sorted(pairs.items()))
    text = (f"window {ns_to_seconds(w.stamp_ns):.3f}: {w.n_views} views, {w.n_keypoints} keypoints, {len(tracks)} tracks "
            f"(length: {', '.join(f'{k}x{n}' for k, n in sorted(lengths.items())) or '-'}); "
            f"matches {per_pair or 'none'}; {sum(len(s) for s, _ in soft.values())} soft pairs > {min_score}; "
            f"latency {1e3 * w.latency_seconds:.1f} ms ({w.method})")
    return {"arrays": w, "tracks": tracks, "pairs": pairs, "soft": soft, "text": text}


class MatchConsumer(Node):
    """Logs a summary of every received window (throttled) and, when the producer tracks
    persistent landmarks, their statistics: landmarks in the window, how many the previous
    window had too, and their ages; keeps the last window."""

    def __init__(self, node_name: str = "match_consumer", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.landmarks_seen = set()   # every landmark id so far (a mapping node would keep a map)
        self._previous_landmarks = set()
        self.windows = 0
        self.malformed = 0
        self.last = None
        self.create_subscription(MatchWindow, "matches", self._on_window, QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.get_logger().info(f"listening on {self.resolve_topic_name('matches')}")

    def _on_window(self, msg: MatchWindow) -> None:
        try:
            summary = summarize(msg)
        except MatchWindowError as exc:
            self.malformed += 1
            self.get_logger().warning(f"malformed MatchWindow ({exc.reason}): {exc}", throttle_duration_sec=5.0)
            return
        self.windows += 1
        self.last = summary
        # Use the data here: e.g. triangulate every track seen in >= 3 views.
        long_tracks = [t for t in summary["tracks"] if len(t) >= 3]
        w = summary["arrays"]
        landmarks = ""
        if w.landmark_ids is not None:
            ids = w.landmark_ids[w.landmark_ids >= 0]
            current = set(ids.tolist())
            ages = w.landmark_ages[w.landmark_ids >= 0]
            landmarks = (f"; landmarks: {len(current)} in the window, {len(current & self._previous_landmarks)} "
                         f"continued, {len(current - self.landmarks_seen)} new, median age "
                         f"{float(np.median(ages)) if ages.size else 0.0:.1f} s, {len(self.landmarks_seen | current)} so far")
            self.landmarks_seen |= current
            self._previous_landmarks = current
        self.get_logger().info(f"{summary['text']}; {len(long_tracks)} tracks in >= 3 views{landmarks} "
                               f"[{self.windows} windows so far]", throttle_duration_sec=2.0)


def main(args=None) -> int:
    """Console script ``match_consumer``."""
    return run_node(MatchConsumer, "match_consumer", args)


if __name__ == "__main__":
    sys.exit(main())
