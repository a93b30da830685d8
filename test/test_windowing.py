"""Windowing (gcn_match_ros.windowing): the same windows online and offline, drops by reason."""
import zlib

import numpy as np
import pytest

from gcn_match_ros.stamps import seconds_to_ns
from gcn_match_ros.windowing import (Frame, FrameError, WindowAssembler, WindowConfig, kept_rows, validate_frame,
                                     window_parameters, window_problem)


def frame(cam, seconds, n=5, dim=8, **kw):
    # deterministic per (camera, stamp); str hash() changes per process and stamps may be < 0
    rng = np.random.default_rng([zlib.crc32(cam.encode()), int(round(seconds * 1000)) % 2 ** 32])
    return Frame(camera_id=cam, stamp_ns=seconds_to_ns(seconds), keypoints=rng.uniform(0, 100, (n, 2)),
                 descriptors=rng.normal(size=(n, dim)), **kw)


CAMS = ("a", "b", "c")


def test_complete_window_emitted_at_once_in_camera_order():
    asm = WindowAssembler(WindowConfig(cameras=CAMS, sync_tolerance=0.01))
    assert asm.add(frame("c", 1.000)) == [] and asm.add(frame("a", 1.004)) == []
    (window,) = asm.add(frame("b", 0.996))
    assert [f.camera_id for f in window] == ["a", "b", "c"]
    p = window_problem(window)
    assert p.n_views == 3 and p.n_keypoints == 15


def test_tolerance_is_exact_to_the_nanosecond():
    asm = WindowAssembler(WindowConfig(cameras=("a", "b"), sync_tolerance=0.01, max_delay=0.0))
    base = 1_700_000_000 * 10**9
    asm.add(Frame("a", base, np.zeros((2, 2)), np.ones((2, 4))))
    (w,) = asm.add(Frame("b", base + 10_000_000, np.zeros((2, 2)), np.ones((2, 4))))  # exactly 10 ms: joins
    assert [f.stamp_ns for f in w] == [base, base + 10_000_000]
    asm.add(Frame("a", base + 10**9, np.zeros((2, 2)), np.ones((2, 4))))
    asm.add(Frame("b", base + 10**9 + 10_000_001, np.zeros((2, 2)), np.ones((2, 4))))  # 1 ns too far
    assert asm.drops["incomplete"] == 1


def test_silent_camera_does_not_stop_windows():
    asm = WindowAssembler(WindowConfig(cameras=CAMS, sync_tolerance=0.01, min_views=2, max_delay=0.05))
    out = []
    for k in range(5):
        t = k * 0.1
        out += asm.add(frame("a", t))
        out += asm.add(frame("b", t + 0.002))
    # Each window is settled once the next period's frames prove camera c will not come.
    assert len(out) == 4 and all(len(w) == 2 for w in out)
    assert len(asm.flush()) == 1


def test_too_few_views_dropped_and_counted():
    asm = WindowAssembler(WindowConfig(cameras=CAMS, sync_tolerance=0.01, min_views=3, max_delay=0.0))
    asm.add(frame("a", 0.0))
    asm.add(frame("b", 0.0))
    assert asm.add(frame("a", 0.5)) == []
    assert asm.drops["incomplete"] == 2


@pytest.mark.parametrize("bad, reason", [
    (dict(keypoints=np.zeros((5, 3))), "bad_shape"),
    (dict(descriptors=np.zeros((4, 8))), "count_mismatch"),
    (dict(descriptors=np.full((5, 8), np.nan)), "non_finite"),
    (dict(keypoints=np.zeros((0, 2)), descriptors=np.zeros((0, 8))), "empty"),
    (dict(descriptors=np.zeros((5, 16))), "descriptor_dim"),
    (dict(scales=np.ones(3)), "bad_shape"),
    (dict(K=np.ones((2, 2))), "bad_intrinsics"),
    (dict(K=np.diag([-500.0, 500.0, 1.0])), "bad_intrinsics"),  # a focal length of 0 on average
    (dict(K=np.diag([0.0, 500.0, 1.0])), "bad_intrinsics"),     # singular, yet not ROS's all-zero "uncalibrated"
    (dict(stamp_ns=1.5e9), "bad_stamp"),
])
def test_bad_frames_are_counted_never_raised(bad, reason):
    asm = WindowAssembler(WindowConfig(cameras=CAMS, descriptor_dim=8))
    f = frame("a", 1.0)
    for key, val in bad.items():
        setattr(f, key, val)
    assert asm.add(f) == []
    assert asm.drops[reason] == 1
    if reason != "bad_stamp":
        with pytest.raises(FrameError):
            validate_frame(f, asm.config, asm.descriptor_dim)


def test_descriptor_dim_zero_takes_the_first_frames():
    asm = WindowAssembler(WindowConfig(cameras=CAMS))
    assert asm.descriptor_dim == 0
    asm.add(frame("a", 1.0, dim=16))
    assert asm.descriptor_dim == 16
    asm.add(frame("b", 1.0, dim=8))
    assert asm.drops["descriptor_dim"] == 1
    asm.reconfigure(WindowConfig(cameras=CAMS, descriptor_dim=0))  # 0 again: the next frame decides
    asm.add(frame("c", 1.0, dim=8))
    assert asm.descriptor_dim == 8
    with pytest.raises(ValueError, match="cameras"):
        asm.reconfigure(WindowConfig(cameras=("a", "b")))


def test_out_of_order_future_unknown_and_stale():
    asm = WindowAssembler(WindowConfig(cameras=CAMS, max_age=1.0, max_future=2.0))
    now = seconds_to_ns(10.0)
    asm.add(frame("a", 10.0), now_ns=now)
    asm.add(frame("a", 9.0), now_ns=now)
    asm.add(frame("a", 100.0), now_ns=now)
    asm.add(frame("z", 10.0))
    asm.add(frame("b", 12.0), now_ns=seconds_to_ns(12.0))  # a@10 is now 2 s behind: stale
    assert asm.drops["out_of_order"] == 1 and asm.drops["future"] == 1
    assert asm.drops["unknown_camera"] == 1 and asm.drops["stale"] == 1


def test_huge_frame_keeps_best_scored_keypoints():
    cfg = WindowConfig(cameras=CAMS, max_keypoints=10)
    f = frame("a", 0.0, n=50)
    f.scores = np.arange(50.0)
    clean = validate_frame(f, cfg)
    assert clean.count == 10
    np.testing.assert_array_equal(clean.scores, np.arange(40.0, 50.0))


def test_kept_rows_is_the_one_trimming_rule():
    scores = np.array([0.1, 0.9, 0.5, 0.9, 0.2])
    np.testing.assert_array_equal(kept_rows(5, scores, 3), [1, 2, 3])  # best three, original order
    np.testing.assert_array_equal(kept_rows(5, None, 3), [0, 1, 2])  # no scores: the first
    np.testing.assert_array_equal(kept_rows(5, scores, 9), np.arange(5))
    f = frame("a", 0.0, n=5, scores=scores)
    clean = validate_frame(f, WindowConfig(cameras=CAMS, max_keypoints=3))
    np.testing.assert_array_equal(clean.keypoints, f.keypoints[kept_rows(5, scores, 3)].astype(np.float32))


def test_uncalibrated_zero_k_becomes_none_and_buffers_are_bounded():
    assert validate_frame(frame("a", 0.0, K=np.zeros((3, 3)))).K is None
    asm = WindowAssembler(WindowConfig(cameras=CAMS, buffer_size=2, sync_tolerance=0.001, max_age=100))
    for k in range(5):
        asm.add(frame("a", k * 0.0001))  # all within tolerance of each other, never a 2nd camera
    assert asm.drops["overflow"] == 3


def test_window_parameters_are_the_config_defaults():
    params = {p.name: p for p in window_parameters()}
    assert list(params) == ["sync_tolerance", "max_delay", "min_views", "max_age", "max_keypoints", "descriptor_dim"]
    cfg = WindowConfig(cameras=CAMS)
    for name, p in params.items():
        assert getattr(cfg, name) == p.default and p.doc and p.low <= p.default <= p.high


def _run(order, **cfg):
    asm = WindowAssembler(WindowConfig(cameras=CAMS, sync_tolerance=0.01, **cfg))
    out = []
    for c, t in order:
        out += asm.add(frame(c, t))
    out += asm.flush()
    return [[(f.camera_id, f.stamp_ns) for f in w] for w in out], asm


def test_identical_windows_from_any_arrival_order():
    periods = [[(c, k * 0.1 + off) for c, off in zip(CAMS, (0.0, 0.003, -0.002))] for k in range(6)]
    in_stamp_order = sorted(sum(periods, []), key=lambda x: x[1])
    reversed_cameras = sum((p[::-1] for p in periods), [])
    windows, _ = _run(in_stamp_order)
    assert windows == _run(reversed_cameras)[0] and len(windows) == 6 and all(len(w) == 3 for w in windows)


def test_a_camera_arriving_late_still_joins_within_max_delay():
    # Camera c's frames arrive 1.5 periods after a's and b's of the same stamp.
    arrivals = []
    for k in range(8):
        arrivals += [("a", k * 0.1), ("b", k * 0.1 + 0.002)]
        if k >= 1:
            arrivals.append(("c", (k - 1) * 0.1 - 0.001))
    complete, _ = _run(arrivals, max_delay=0.25)
    assert sum(len(w) == 3 for w in complete) == 7
    impatient, asm = _run(arrivals, max_delay=0.0)
    assert sum(len(w) == 3 for w in impatient) == 0 and asm.drops["out_of_order"] == 0


def test_absurd_or_out_of_image_keypoints_and_descriptors_are_refused():
    """Finite but meaningless input (e.g. 1e30) would make the similarity NaN and lose the whole
    window as a solver error; it is refused per frame instead, with its own reason."""
    import dataclasses

    from gcn_match_ros.problem import MAX_ABS_DESCRIPTOR, MAX_ABS_PIXEL

    rng = np.random.default_rng(0)
    kp, desc = rng.uniform(0, 400, (10, 2)), rng.random((10, 8))

    def frame(**changes):
        f = Frame(camera_id="cam0", stamp_ns=1, keypoints=kp, descriptors=desc)
        return dataclasses.replace(f, **changes)

    validate_frame(frame())
    validate_frame(frame(image_size=(640, 480)))
    for changes in ({"keypoints": np.where(np.arange(10)[:, None] == 3, 1e30, kp)},
                    {"keypoints": kp + 2 * MAX_ABS_PIXEL},
                    {"keypoints": kp + [0, 300], "image_size": (640, 480)},   # below the image
                    {"keypoints": kp - 5, "image_size": (640, 480)},          # left of / above it
                    {"descriptors": desc * 2 * MAX_ABS_DESCRIPTOR}):
        with pytest.raises(FrameError) as err:
            validate_frame(frame(**changes))
        assert err.value.reason == "out_of_range"
    # a keypoint refined to just past the border is fine
    validate_frame(frame(keypoints=np.vstack([kp[:-1], [640.5, 0.0]]), image_size=(640, 480)))
