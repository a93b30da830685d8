"""ROS message conversions (gcn_match_ros.ros.conversions, with the Keypoints codec of
gcn_match_ros.bags.codec): no node, no DDS."""
from __future__ import annotations

import array

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message

from gcn_match_msgs.msg import Keypoints
from gcn_match_ros.bags.codec import frame_from_keypoints_msg
from gcn_match_ros.problem import Result
from gcn_match_ros.ros.conversions import (MatchWindowError, frame_to_keypoints, match_window_to_arrays, ns_to_time,
                                           pairwise_matches, result_to_match_window, soft_pairwise_matches,
                                           validate_match_window, window_tracks)
from gcn_match_ros.stamps import stamp_to_ns
from gcn_match_ros.windowing import Frame, FrameError

from conftest import PermutedScene

CAMS = ["cam0", "cam1", "cam2"]


def _roundtrip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def test_keypoints_frame_roundtrip_float_descriptors():
    f, _ = PermutedScene(points=30, dim=128, seed=1).frame("cam1", 1_700_000_000.123456789)
    f.stamp_ns = 1_700_000_000_123_456_789  # exact to the nanosecond
    f.scores = np.linspace(1, 0, f.count).astype(np.float32)
    msg = _roundtrip(frame_to_keypoints(f))
    assert msg.descriptor_type == Keypoints.DESCRIPTOR_FLOAT and msg.descriptor_name == "sift"
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 123_456_789)
    g = frame_from_keypoints_msg(msg)
    assert g.camera_id == "cam1" and g.frame_id == "cam1_optical_frame" and g.stamp_ns == f.stamp_ns
    assert not g.binary and g.descriptor_name == "sift"
    np.testing.assert_array_equal(g.keypoints, f.keypoints)
    np.testing.assert_array_equal(g.descriptors, f.descriptors)
    for name in ("scales", "orientations", "scores"):
        np.testing.assert_array_equal(getattr(g, name), getattr(f, name))
    np.testing.assert_allclose(g.K, f.K)
    assert g.image_size == (640, 480)
    assert msg.camera_info.distortion_model == "plumb_bob" and list(msg.camera_info.p[:3]) == list(f.K[0])
    # All-zero k = uncalibrated; empty optional arrays stay None.
    f2 = Frame(camera_id="c", stamp_ns=2 * 10**9, keypoints=np.zeros((3, 2)), descriptors=np.ones((3, 4)))
    g2 = frame_from_keypoints_msg(_roundtrip(frame_to_keypoints(f2)))
    assert g2.K is None and g2.scales is None and g2.image_size is None and g2.descriptors.shape == (3, 4)
    t = ns_to_time(12_000_000_001)
    assert (t.sec, t.nanosec) == (12, 1) and stamp_to_ns(t) == 12_000_000_001


@pytest.mark.parametrize("dim", [256, 250])
def test_keypoints_frame_roundtrip_binary_descriptors(dim):
    rng = np.random.default_rng(dim)
    bits = rng.integers(0, 2, size=(40, dim)).astype(np.float32)
    f = Frame(camera_id="cam0", stamp_ns=5 * 10**9, keypoints=rng.uniform(0, 100, (40, 2)), descriptors=bits,
              binary=True, descriptor_name="orb")
    msg = _roundtrip(frame_to_keypoints(f))
    assert msg.descriptor_type == Keypoints.DESCRIPTOR_BINARY and msg.descriptor_dim == dim
    assert len(msg.descriptors) == 0 and len(msg.descriptors_binary) == 40 * ((dim + 7) // 8)
    g = frame_from_keypoints_msg(msg)
    assert g.descriptors.dtype == np.float32 and g.binary and g.descriptor_name == "orb"
    np.testing.assert_array_equal(g.descriptors, bits)
    # Same packing as OpenCV/np.packbits (MSB first).
    np.testing.assert_array_equal(np.frombuffer(msg.descriptors_binary, np.uint8).reshape(40, -1),
                                  np.packbits(bits.astype(np.uint8), axis=1))
    # A binary frame must hold bits.
    with pytest.raises(ValueError, match="unpacked bits"):
        frame_to_keypoints(Frame(camera_id="cam0", stamp_ns=0, keypoints=np.zeros((2, 2)),
                                 descriptors=np.full((2, 8), 0.5), binary=True))


def _good_msg(n=10, dim=8) -> Keypoints:
    rng = np.random.default_rng(0)
    return frame_to_keypoints(Frame(camera_id="cam0", stamp_ns=10**9, keypoints=rng.uniform(0, 9, (n, 2)),
                                    descriptors=rng.normal(size=(n, dim))))


@pytest.mark.parametrize("breaker,reason", [
    (lambda m: setattr(m, "count", m.count + 1), "count_mismatch"),
    (lambda m: setattr(m, "descriptors", array.array("f", [0.0] * 7)), "count_mismatch"),
    (lambda m: setattr(m, "descriptor_type", 7), "descriptor_type"),
    (lambda m: setattr(m, "descriptor_dim", 0), "descriptor_dim"),
    (lambda m: setattr(m, "scales", array.array("f", [1.0] * 3)), "bad_shape"),
    (lambda m: setattr(m, "descriptors_binary", array.array("B", [1])), "bad_shape"),
    (lambda m: setattr(m, "count", 10 ** 9), "too_large"),
    (lambda m: setattr(m, "camera_id", "cam9"), "camera_mismatch"),
])
def test_malformed_keypoints_raise_frame_error(breaker, reason):
    msg = _good_msg()
    breaker(msg)
    with pytest.raises(FrameError) as exc:
        frame_from_keypoints_msg(msg, camera_id="cam0")
    assert exc.value.reason == reason


def test_match_window_shapes_tracks_and_pairs():
    scene = PermutedScene(points=6, dim=8, distractors=1, seed=3)
    frames = [scene.frame(c, 10.0 + 0.01 * i)[0] for i, c in enumerate(CAMS)]
    # Tracks: keypoint 0 of every view together, keypoint 1 of views 0 and 2; one pair score.
    n = sum(f.count for f in frames)
    track = np.full(n, -1)
    track[[0, 7, 14]] = 5
    track[[1, 15]] = 9
    result = Result(track=track, pair_rows=[0, 1, 2], pair_cols=[7, 15, 8], pair_scores=[0.9, 0.6, 0.05],
                    method="test")
    msg = _roundtrip(result_to_match_window(frames, result, score_threshold=0.1, dense=True, latency_seconds=0.01))
    validate_match_window(msg)
    assert list(msg.camera_ids) == CAMS and list(msg.view_offsets) == [0, 7, 14, 21]
    assert msg.track_count == 2 and len(msg.track) == n and len(msg.dense_scores) == n * n
    assert list(msg.pair_rows) == [0, 1] and list(msg.pair_cols) == [7, 15]  # 0.05 is below the threshold
    assert stamp_to_ns(msg.header.stamp) == frames[2].stamp_ns  # the newest view
    assert [stamp_to_ns(s) for s in msg.view_stamps] == [f.stamp_ns for f in frames]
    w = match_window_to_arrays(msg)
    assert w.stamp_ns == frames[2].stamp_ns and w.view_stamps_ns.tolist() == [f.stamp_ns for f in frames]
    assert w.dense_scores.shape == (n, n) and w.dense_scores[0, 7] == pytest.approx(0.9)
    assert w.dense_scores[2, 8] == pytest.approx(0.05) and w.dense_scores[3, 3] == 1.0
    tracks = window_tracks(msg)
    assert sorted(map(sorted, tracks)) == [[(0, 0), (1, 0), (2, 0)], [(0, 1), (2, 1)]]
    pairs = pairwise_matches(w)
    assert pairs[(0, 1)].tolist() == [[0, 0]] and sorted(pairs[(0, 2)].tolist()) == [[0, 0], [1, 1]]
    soft = soft_pairwise_matches(w, min_score=0.5)
    assert soft[(0, 2)][0].tolist() == [[1, 1]] and soft[(0, 2)][1].tolist() == [pytest.approx(0.6)]

    # Inconsistent results never become messages.
    bad = [
        Result(track=track[:-1], pair_rows=[], pair_cols=[], pair_scores=[]),          # wrong length
        Result(track=track, pair_rows=[0], pair_cols=[3], pair_scores=[0.5]),           # same view
        Result(track=np.where(np.arange(n) == 2, 5, track), pair_rows=[], pair_cols=[], pair_scores=[]),
        Result(track=track, pair_rows=[0], pair_cols=[n + 3], pair_scores=[0.5]),       # out of range
    ]
    for r in bad:
        with pytest.raises(MatchWindowError):
            result_to_match_window(frames, r)
    # A corrupted message is caught by the validator (consumers call it via match_window_to_arrays).
    broken = _roundtrip(msg)
    broken.track = array.array("i", [0] * (n - 1))
    with pytest.raises(MatchWindowError):
        match_window_to_arrays(broken)
    # ... and a consumer node's decode counts and logs it instead of raising
    from collections import Counter
    from gcn_match_ros.ros.frame_buffer import decoded_window

    class Logger:
        def __init__(self):
            self.warnings = []

        def warning(self, text, throttle_duration_sec):
            self.warnings.append((text, throttle_duration_sec))

    counts, logger = Counter(), Logger()
    assert decoded_window(broken, counts, logger, 2.0) is None
    assert counts["invalid windows"] == 1 and logger.warnings[0][0].startswith("skipped an invalid window")
    assert logger.warnings[0][1] == 2.0
    assert decoded_window(msg, counts, logger, 2.0).stamp_ns == frames[2].stamp_ns and counts["invalid windows"] == 1


def test_landmark_fields_round_trip_and_are_validated():
    frames = [PermutedScene(points=6, dim=8, distractors=0, seed=s).frame(f"cam{s}", 1.0 + s)[0] for s in range(2)]
    track = np.r_[np.arange(6), np.arange(6)]
    result = Result(track=track, pair_rows=np.zeros(0, np.int64), pair_cols=np.zeros(0, np.int64),
                    pair_scores=np.zeros(0, np.float32))
    ids = np.r_[np.arange(6) + 100, np.arange(6) + 100]
    ids[0] = ids[6] = -1
    msg = result_to_match_window(frames, result, landmark_ids=ids, landmark_ages=np.full(12, 2.5))
    w = match_window_to_arrays(msg)
    np.testing.assert_array_equal(w.landmark_ids, ids)
    assert w.landmark_ages[0] == -1.0 and w.landmark_ages[1] == 2.5
    assert match_window_to_arrays(result_to_match_window(frames, result)).landmark_ids is None
    with pytest.raises(MatchWindowError, match="landmarks"):
        result_to_match_window(frames, result, landmark_ids=ids[:5], landmark_ages=np.zeros(5))
    msg.landmark_ages = msg.landmark_ages[:3]
    with pytest.raises(MatchWindowError, match="landmark_ids / landmark_ages"):
        validate_match_window(msg)
