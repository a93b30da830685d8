"""The matcher node's counters and its ``/diagnostics`` report.

:class:`MatcherStats` is shared by the subscription callbacks, the inference worker and the
diagnostics timer (the node holds its lock around every call). :meth:`MatcherStats.report`
turns it, with the assembler's drop counters, into one ``DiagnosticStatus``: WARN when frames
or windows were dropped since the last report or a camera fell silent, OK otherwise, and the
values a user looks at (rates per camera, windows/s, latency and compute percentiles, drops
by reason).
"""
from __future__ import annotations

import collections
import math
import time
from typing import Dict, List, Mapping, Optional, Sequence

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

__all__ = ["STATS_HORIZON_S", "MatcherStats"]

#: Latency / compute percentiles in the diagnostics cover this many recent seconds.
STATS_HORIZON_S = 10.0


def _percentile(values, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def _fmt(value: float, scale: float = 1.0, digits: int = 1) -> str:
    return "nan" if not math.isfinite(value) else f"{value * scale:.{digits}f}"


class MatcherStats:
    """Counters of one matcher node (not thread-safe by itself)."""

    def __init__(self, cameras: Sequence[str]) -> None:
        self.cameras = tuple(cameras)
        self.received = collections.Counter({c: 0 for c in cameras})
        self.last_received: Dict[str, float] = {}
        self.conversion_drops: collections.Counter = collections.Counter()
        self.window_drops: collections.Counter = collections.Counter()
        self.truncated = 0
        self.published = 0
        self.recent: collections.deque = collections.deque()  # (monotonic, latency s, compute s, association s)
        # values at the previous report, for rates
        self._prev_time = time.monotonic()
        self._prev_received = collections.Counter(self.received)
        self._prev_published = 0
        self._prev_drops = 0

    def frame_received(self, camera: str) -> None:
        self.received[camera] += 1
        self.last_received[camera] = time.monotonic()

    def window_published(self, latency: float, compute: float, association: float = float("nan")) -> None:
        """One window out: its latency and compute seconds, and the part of the compute its
        landmark association took (NaN: none associated)."""
        self.published += 1
        self.recent.append((time.monotonic(), latency, compute, association))

    def report(self, name: str, hardware_id: str, assembler_drops: Mapping[str, int], descriptor_dim: int,
               busy: bool, pending: bool, stale_after: float, extra: Optional[Mapping[str, str]] = None,
               warnings: Sequence[str] = ()) -> DiagnosticStatus:
        """The status since the previous report (rates and new drops are counted from it);
        ``warnings``: further conditions that make it WARN (e.g. degraded under load)."""
        mono = time.monotonic()
        while self.recent and self.recent[0][0] < mono - STATS_HORIZON_S:
            self.recent.popleft()
        lat = [r[1] for r in self.recent]
        comp = [r[2] for r in self.recent]
        association = [r[3] for r in self.recent if math.isfinite(r[3])]
        elapsed = max(mono - self._prev_time, 1e-6)
        rates = {c: (self.received[c] - self._prev_received[c]) / elapsed for c in self.cameras}
        frame_drops = collections.Counter(assembler_drops) + self.conversion_drops
        total_drops = sum(frame_drops.values()) + sum(self.window_drops.values())
        new_drops = total_drops - self._prev_drops
        win_rate = (self.published - self._prev_published) / elapsed
        self._prev_time, self._prev_received = mono, collections.Counter(self.received)
        self._prev_published, self._prev_drops = self.published, total_drops

        silent = [c for c in self.cameras
                  if c not in self.last_received or mono - self.last_received[c] > stale_after]
        problems: List[str] = []
        if new_drops:
            problems.append(f"{new_drops} drops since the last report")
        if silent:
            problems.append(f"no input from {', '.join(silent)}")
        problems.extend(warnings)
        values: Dict[str, str] = {
            **(extra or {}),
            "cameras": ",".join(self.cameras),
            "windows/s": _fmt(win_rate, digits=2),
            "windows published": str(self.published),
            "latency p50 [ms]": _fmt(_percentile(lat, 50), 1e3),
            "latency p95 [ms]": _fmt(_percentile(lat, 95), 1e3),
            "latency max [ms]": _fmt(max(lat) if lat else float("nan"), 1e3),
            "compute p50 [ms]": _fmt(_percentile(comp, 50), 1e3),
            "compute p95 [ms]": _fmt(_percentile(comp, 95), 1e3),
            "landmark association p50 [ms]": _fmt(_percentile(association, 50), 1e3, digits=2),
            "worker": "busy" if busy else "idle",
            "window pending": str(pending),
            "descriptor dim": str(descriptor_dim),
            "frames truncated": str(self.truncated),
            "frames dropped total": str(sum(frame_drops.values())),
            "windows dropped total": str(sum(self.window_drops.values())),
        }
        for cam in self.cameras:
            values[f"input rate {cam} [Hz]"] = _fmt(rates[cam], digits=2)
            values[f"frames received {cam}"] = str(self.received.get(cam, 0))
        for reason, n in sorted(frame_drops.items()):
            values[f"frames dropped {reason}"] = str(n)
        for reason, n in sorted(self.window_drops.items()):
            values[f"windows dropped {reason}"] = str(n)
        return DiagnosticStatus(level=DiagnosticStatus.WARN if problems else DiagnosticStatus.OK, name=name,
                                message="; ".join(problems) or "ok", hardware_id=hardware_id,
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])
