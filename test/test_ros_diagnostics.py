"""Tests of gcn_match_ros.ros.diagnostics: MatcherStats.report levels, drops counted once, rates and values."""
import types

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from gcn_match_ros.ros import diagnostics
from gcn_match_ros.ros.diagnostics import STATS_HORIZON_S, MatcherStats

CAMS = ("cam0", "cam1")


class Clock:
    """A monotonic clock the test moves by hand."""

    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def monotonic(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(diagnostics, "time", types.SimpleNamespace(monotonic=c.monotonic))
    return c


def report(stats, assembler_drops=None, stale_after=2.0, **kw):
    st = stats.report("matcher_node: matching", "/matcher_node", assembler_drops or {}, 128, busy=False,
                      pending=False, stale_after=stale_after, **kw)
    return st, {kv.key: kv.value for kv in st.values}


def test_ok_with_no_drops_and_every_camera_recent(clock):
    stats = MatcherStats(CAMS)
    for _ in range(4):
        clock.now += 0.25
        stats.frame_received("cam0")
        stats.frame_received("cam1")
    stats.frame_received("cam1")
    stats.window_published(latency=0.030, compute=0.010)
    stats.window_published(latency=0.050, compute=0.020, association=0.004)
    st, values = report(stats, extra={"solver": "nn"})
    assert st.level == DiagnosticStatus.OK and st.message == "ok"
    assert (st.name, st.hardware_id) == ("matcher_node: matching", "/matcher_node")
    assert list(values)[0] == "solver" and values["solver"] == "nn"  # extra values come first
    assert values["cameras"] == "cam0,cam1"
    # one second since the stats were made: rates are counts per second
    assert values["input rate cam0 [Hz]"] == "4.00" and values["input rate cam1 [Hz]"] == "5.00"
    assert values["frames received cam0"] == "4" and values["frames received cam1"] == "5"
    assert values["windows/s"] == "2.00" and values["windows published"] == "2"
    assert values["latency p50 [ms]"] == "40.0" and values["latency max [ms]"] == "50.0"
    assert values["compute p50 [ms]"] == "15.0"
    assert values["landmark association p50 [ms]"] == "4.00"   # of the windows that associated
    assert values["worker"] == "idle" and values["window pending"] == "False" and values["descriptor dim"] == "128"
    assert values["frames dropped total"] == "0" and values["windows dropped total"] == "0"
    assert not any(k.startswith(("frames dropped ", "windows dropped ")) and "total" not in k for k in values)


def test_new_drops_warn_once(clock):
    stats = MatcherStats(CAMS)
    clock.now += 0.5
    stats.frame_received("cam0")
    stats.frame_received("cam1")
    stats.conversion_drops["bad message"] += 1
    stats.window_drops["solver error"] += 1
    st, values = report(stats, assembler_drops={"late": 2, "future": 1})
    assert st.level == DiagnosticStatus.WARN
    assert st.message == "5 drops since the last report"
    assert values["frames dropped late"] == "2" and values["frames dropped future"] == "1"
    assert values["frames dropped bad message"] == "1" and values["windows dropped solver error"] == "1"
    assert values["frames dropped total"] == "4" and values["windows dropped total"] == "1"
    # the next report without new drops is OK again (the cameras are still recent); totals stay
    clock.now += 0.5
    stats.frame_received("cam0")
    stats.frame_received("cam1")
    st, values = report(stats, assembler_drops={"late": 2, "future": 1})
    assert st.level == DiagnosticStatus.OK and st.message == "ok"
    assert values["frames dropped late"] == "2" and values["frames dropped total"] == "4"
    # only the new drops are counted
    stats.window_drops["queue full"] += 1
    st, _ = report(stats, assembler_drops={"late": 3, "future": 1})
    assert st.level == DiagnosticStatus.WARN and st.message == "2 drops since the last report"


def test_a_silent_camera_warns(clock):
    stats = MatcherStats(("cam0", "cam1", "cam2"))
    stats.frame_received("cam0")
    stats.frame_received("cam1")
    clock.now += 1.0
    st, values = report(stats, stale_after=2.0)
    assert st.level == DiagnosticStatus.WARN and st.message == "no input from cam2"  # never heard from
    assert values["frames received cam2"] == "0" and values["input rate cam2 [Hz]"] == "0.00"
    clock.now += 1.5  # cam0 and cam1 last heard 2.5 s ago; cam1 speaks again
    stats.frame_received("cam1")
    stats.frame_received("cam2")
    st, _ = report(stats, stale_after=2.0)
    assert st.level == DiagnosticStatus.WARN and st.message == "no input from cam0"
    stats.frame_received("cam0")
    stats.window_drops["stale"] += 1
    st, _ = report(stats, stale_after=2.0)
    assert st.level == DiagnosticStatus.WARN and st.message == "1 drops since the last report"
    clock.now += 5.0
    st, _ = report(stats, stale_after=2.0)  # drops and silence together
    assert st.message == "no input from cam0, cam1, cam2"
    stats.window_drops["stale"] += 1
    st, _ = report(stats, stale_after=2.0)
    assert st.message == "1 drops since the last report; no input from cam0, cam1, cam2"


def test_latency_percentiles_cover_the_recent_horizon(clock):
    stats = MatcherStats(CAMS)
    st, values = report(stats, stale_after=100.0)
    assert values["latency p50 [ms]"] == "nan" and values["windows/s"] == "0.00"  # nothing yet
    stats.window_published(latency=1.0, compute=0.5)
    clock.now += STATS_HORIZON_S + 1.0
    stats.window_published(latency=0.010, compute=0.005)
    _, values = report(stats, stale_after=100.0)
    assert values["latency max [ms]"] == "10.0" and values["compute p95 [ms]"] == "5.0"  # the old one left
    assert values["windows published"] == "2"
