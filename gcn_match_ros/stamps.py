"""Time stamps as integer nanoseconds, as rosbag2 and rclpy keep them.

A ``builtin_interfaces/Time`` is (sec, nanosec); a bag's log time and rclpy's clock are
integer nanoseconds. Every stamp in this package is an int of nanoseconds too
(``Frame.stamp_ns``), so a stamp survives message -> core -> message unchanged; this module
is the one place that converts. Durations (the window parameters) are given in seconds and
turned into nanoseconds once, by :func:`duration_ns`.
"""
from __future__ import annotations

import math
from typing import Tuple

__all__ = ["NS_PER_S", "stamp_to_ns", "ns_to_sec_nanosec", "ns_to_seconds", "seconds_to_ns", "duration_ns"]

NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp) -> int:
    """A ``builtin_interfaces/Time`` (rclpy or rosbags message: ``sec``, ``nanosec``) -> ns."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_sec_nanosec(ns: int) -> Tuple[int, int]:
    """ns -> (sec, nanosec) of a ``builtin_interfaces/Time`` (nanosec in [0, 1e9))."""
    return divmod(int(ns), NS_PER_S)


def ns_to_seconds(ns: int) -> float:
    """ns -> float seconds, for display and rates (a float holds epoch seconds only to
    ~0.24 µs: never compare or store stamps this way)."""
    sec, nsec = divmod(int(ns), NS_PER_S)
    return sec + nsec * 1e-9


def seconds_to_ns(seconds: float) -> int:
    """Float seconds -> ns, such that ``ns_to_seconds(seconds_to_ns(s)) == s`` whenever some
    integer ns reads back as ``s`` (every float made by :func:`ns_to_seconds` does); else the
    nearest ns.

    Several ns values map to one float; this picks the roundest of them
    (``1700000000.102`` -> ``1700000000102000000``, not ``...101999998``), so stamps made
    from round numbers stay round.

    Raises:
        ValueError: not finite.
    """
    f = float(seconds)
    if not math.isfinite(f):
        raise ValueError(f"stamp must be finite, got {seconds!r}")
    sec = math.floor(f)
    base = sec * NS_PER_S + int(round((f - sec) * 1e9))  # f - sec is exact
    for q in (10**9, 10**8, 10**7, 10**6, 10**5, 10**4, 10**3, 10**2, 10):
        cand = (base + q // 2) // q * q
        if ns_to_seconds(cand) == f:
            return cand
    return base


def duration_ns(seconds: float) -> int:
    """A duration in seconds -> ns (rounded to the nearest ns)."""
    return int(round(float(seconds) * 1e9))
