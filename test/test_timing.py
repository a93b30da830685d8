"""Tests of gcn_match_ros.timing: stages are recorded only when asked, exclusive of nested stages."""
import threading
import time

from gcn_match_ros.timing import StageTimes, add_to_active, stage

NAP = 0.01  # seconds; only lower bounds and sums are checked, never how long a sleep took


def test_stage_outside_recording_is_a_no_op():
    times = StageTimes()
    with stage("anything"):
        time.sleep(NAP)
    assert times.seconds == {}
    with times.recording():
        pass
    with stage("after"):  # the recorder was released
        pass
    assert times.seconds == {}


def test_nested_stages_are_exclusive_and_add_up_to_the_wall_time():
    times = StageTimes()
    start = time.perf_counter()
    with times.recording():
        with stage("outer"):
            time.sleep(NAP)
            with stage("inner"):
                time.sleep(3 * NAP)
                with stage("innermost"):
                    time.sleep(NAP)
            time.sleep(NAP)
        with stage("outer"):  # a stage entered again adds up
            time.sleep(NAP)
    wall = time.perf_counter() - start
    s = times.seconds
    assert set(s) == {"outer", "inner", "innermost"}
    assert s["outer"] >= 3 * NAP and s["inner"] >= 3 * NAP and s["innermost"] >= NAP
    # exclusive: inclusive times would add the nested sleeps twice and exceed the wall time
    total = sum(s.values())
    assert total <= wall + 1e-9 and total > 0.5 * wall


def test_recording_restores_the_previous_recorder():
    outer, inner = StageTimes(), StageTimes()
    with outer.recording():
        with stage("a"):
            pass
        with inner.recording():
            with stage("b"):
                pass
        with stage("c"):
            pass
    with stage("d"):
        pass
    assert set(outer.seconds) == {"a", "c"} and set(inner.seconds) == {"b"}


def test_other_threads_do_not_record_into_this_recorder():
    times = StageTimes()

    def elsewhere():
        with stage("other_thread"):
            pass

    with times.recording():
        worker = threading.Thread(target=elsewhere)
        worker.start()
        worker.join()
        with stage("this_thread"):
            pass
    assert set(times.seconds) == {"this_thread"}


def test_stages_timed_on_another_thread_are_added_to_the_active_recorder_only():
    times = StageTimes()
    add_to_active({"elsewhere": 1.0})  # no recorder: nothing to add to
    with times.recording():
        with stage("here"):
            pass
        add_to_active({"elsewhere": 0.25})
        add_to_active({"elsewhere": 0.25, "here": 1.0})
    assert times.seconds["elsewhere"] == 0.5 and times.seconds["here"] >= 1.0
