"""Tests of gcn_match_ros.stamps: integer-nanosecond stamps and their conversions."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from gcn_match_ros.stamps import NS_PER_S, duration_ns, ns_to_sec_nanosec, ns_to_seconds, seconds_to_ns, stamp_to_ns


def _trailing_zeros(ns: int) -> int:
    """Decimal trailing zeros of ns, counted up to whole seconds (9)."""
    zeros = 0
    while zeros < 9 and ns % 10 ** (zeros + 1) == 0:
        zeros += 1
    return zeros


def test_seconds_to_ns_picks_the_roundest_ns_of_the_float():
    assert seconds_to_ns(1700000000.102) == 1700000000102000000
    assert ns_to_seconds(1700000000102000000) == 1700000000.102
    # epoch floats are ~240 ns apart: the plain product lands on a less round ns of the same float
    assert int(round(1700000000.102 * 1e9)) != 1700000000102000000
    # brute force: among every ns that reads back as the same float, none is rounder
    rng = np.random.default_rng(0)
    floats = [1700000000.102, 1700000000.0, 1.5, 0.25, 12.000000001] + \
        list(np.round(rng.uniform(1.6e9, 1.8e9, 20), 3)) + list(rng.uniform(1.6e9, 1.8e9, 20))
    for f in floats:
        f = float(f)
        ns = seconds_to_ns(f)
        assert ns_to_seconds(ns) == f
        same_float = [m for m in range(ns - 1000, ns + 1001) if ns_to_seconds(m) == f]
        assert max(_trailing_zeros(m) for m in same_float) == _trailing_zeros(ns), f


def test_seconds_to_ns_and_back_round_trip():
    rng = np.random.default_rng(1)
    # every float some ns reads back as: epoch floats (~240 ns apart) and floats made from ns
    epoch = list(rng.uniform(1.6e9, 1.8e9, 200))
    from_ns = [ns_to_seconds(int(ns)) for ns in rng.integers(-10**12, 10**12, 200)]
    for s in epoch + from_ns + [0.0, -0.5, -1.25, 3.0]:
        assert ns_to_seconds(seconds_to_ns(float(s))) == float(s)
    assert seconds_to_ns(-0.5) == -500_000_000 and seconds_to_ns(3.0) == 3 * NS_PER_S
    # a float finer than 1 ns has no ns of its own: the nearest one
    assert seconds_to_ns(23.64324940051347) == 23_643_249_401
    # ns -> s -> ns is exact while floats resolve single nanoseconds (here below ~1e6 s)
    for ns in rng.integers(-10**15, 10**15, 200):
        assert seconds_to_ns(ns_to_seconds(int(ns))) == int(ns)


def test_ns_to_sec_nanosec_keeps_nanosec_in_range():
    assert ns_to_sec_nanosec(1700000000102000001) == (1700000000, 102000001)
    assert ns_to_sec_nanosec(0) == (0, 0)
    assert ns_to_sec_nanosec(-1) == (-1, 999_999_999)  # builtin_interfaces/Time: nanosec in [0, 1e9)
    for ns in np.random.default_rng(2).integers(-10**18, 10**18, 100):
        sec, nsec = ns_to_sec_nanosec(int(ns))
        assert 0 <= nsec < NS_PER_S and sec * NS_PER_S + nsec == int(ns)
        assert stamp_to_ns(SimpleNamespace(sec=sec, nanosec=nsec)) == int(ns)


def test_stamp_to_ns_reads_sec_and_nanosec():
    assert stamp_to_ns(SimpleNamespace(sec=1700000000, nanosec=102000001)) == 1700000000102000001
    assert stamp_to_ns(SimpleNamespace(sec=np.int32(5), nanosec=np.uint32(7))) == 5 * NS_PER_S + 7
    assert isinstance(stamp_to_ns(SimpleNamespace(sec=np.int32(5), nanosec=np.uint32(7))), int)


def test_duration_ns_rounds_to_the_nearest_ns():
    assert duration_ns(0.05) == 50_000_000
    assert duration_ns(1e-9) == 1 and duration_ns(0.4e-9) == 0
    assert duration_ns(10) == 10 * NS_PER_S and duration_ns(0.1) == 100_000_000


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_seconds_to_ns_refuses_non_finite(bad):
    with pytest.raises(ValueError, match="finite"):
        seconds_to_ns(bad)
