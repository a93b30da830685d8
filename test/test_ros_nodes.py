"""ROS side: message conversions and the nodes over real DDS.

Every test that talks DDS has its own rclpy Context on a random ROS_DOMAIN_ID and its own
node namespace (so even a domain shared with a concurrent run never mixes topics);
discovery is confined to this machine. Nothing sleeps a fixed time: tests spin the
executor until a condition holds or a timeout passes.

The matcher tests run with ``GCN_MATCH_TEST_SOLVER`` (default: ``gcn`` when its shipped
model exists, else ``nn``); the accuracy test runs every available solver of nn / gcn.
"""
from __future__ import annotations

import array
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"  # no traffic leaves the machine
os.environ.pop("ROS_LOCALHOST_ONLY", None)
if not os.environ.get("ROS_LOG_DIR"):
    os.environ["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix="gcn_match_ros-test-roslog-")

import rclpy  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from rclpy.signals import SignalHandlerOptions  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from gcn_match_msgs.msg import Keypoints, MatchWindow  # noqa: E402
from gcn_match_ros.metrics import score_result  # noqa: E402
from gcn_match_ros.problem import Problem, Result  # noqa: E402
from gcn_match_ros.ros.conversions import (MatchWindowError, frame_to_keypoints, keypoints_to_frame,  # noqa: E402
                                           match_window_to_arrays, pairwise_matches, result_to_match_window,
                                           seconds_to_stamp, soft_pairwise_matches, stamp_to_seconds,
                                           validate_match_window, window_tracks)
from gcn_match_ros.solvers import available_solvers  # noqa: E402
from gcn_match_ros.solvers.base import SoftMatches, Solver, register  # noqa: E402
from gcn_match_ros.windowing import Frame, FrameError  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CAMS = ["cam0", "cam1", "cam2"]
RELIABLE = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE)


def _gcn_model_available() -> bool:
    try:
        from gcn_match_ros.solvers.gcn import DEFAULT_CHECKPOINT
    except ImportError:
        return False
    return Path(DEFAULT_CHECKPOINT).is_file()


TEST_SOLVER = os.environ.get("GCN_MATCH_TEST_SOLVER") or ("gcn" if _gcn_model_available() else "nn")


# ---------------------------------------------------------------------------------------
# Synthetic data: V cameras see the same points in random order (+ distractors)
# ---------------------------------------------------------------------------------------
class PermutedScene:
    """Descriptors of ``points`` scene points; every camera sees all of them permuted, with
    noise, plus a few distractors (gt -1). Keypoint positions are per point + pixel noise."""

    def __init__(self, points: int = 60, dim: int = 128, noise: float = 0.05, distractors: int = 5,
                 seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.base = np.abs(self.rng.normal(size=(points, dim)))
        self.xy = self.rng.uniform(20, 620, size=(points, 2))
        self.points, self.dim, self.noise, self.distractors = points, dim, noise, distractors

    def frame(self, cam: str, stamp: float):
        rng, p = self.rng, self.points
        perm = rng.permutation(p)
        desc = np.abs(self.base[perm] + self.noise * rng.normal(size=(p, self.dim)))
        xy = self.xy[perm] + rng.normal(scale=2.0, size=(p, 2))
        if self.distractors:
            desc = np.vstack([desc, np.abs(rng.normal(size=(self.distractors, self.dim)))])
            xy = np.vstack([xy, rng.uniform(20, 620, size=(self.distractors, 2))])
        gt = np.concatenate([perm, -np.ones(self.distractors, np.int64)])
        f = Frame(camera_id=cam, stamp=stamp, keypoints=xy.astype(np.float32),
                  descriptors=desc.astype(np.float32), frame_id=f"{cam}_optical_frame",
                  scales=np.full(len(gt), 3.0, np.float32), orientations=np.zeros(len(gt), np.float32),
                  K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]), image_size=(640, 480))
        return f, gt


def _roundtrip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


# ---------------------------------------------------------------------------------------
# Conversions (no DDS)
# ---------------------------------------------------------------------------------------
def test_keypoints_frame_roundtrip_float_descriptors():
    f, _ = PermutedScene(points=30, dim=128, seed=1).frame("cam1", 1_700_000_000.123456789)
    f.scores = np.linspace(1, 0, f.count).astype(np.float32)
    msg = _roundtrip(frame_to_keypoints(f, descriptor_name="sift"))
    assert msg.descriptor_type == Keypoints.DESCRIPTOR_FLOAT and msg.descriptor_name == "sift"
    g = keypoints_to_frame(msg)
    assert g.camera_id == "cam1" and g.frame_id == "cam1_optical_frame"
    assert abs(g.stamp - f.stamp) < 1e-6
    np.testing.assert_array_equal(g.keypoints, f.keypoints)
    np.testing.assert_array_equal(g.descriptors, f.descriptors)
    for name in ("scales", "orientations", "scores"):
        np.testing.assert_array_equal(getattr(g, name), getattr(f, name))
    np.testing.assert_allclose(g.K, f.K)
    assert g.image_size == (640, 480)
    # All-zero k = uncalibrated; empty optional arrays stay None.
    f2 = Frame(camera_id="c", stamp=2.0, keypoints=np.zeros((3, 2)), descriptors=np.ones((3, 4)))
    g2 = keypoints_to_frame(_roundtrip(frame_to_keypoints(f2)))
    assert g2.K is None and g2.scales is None and g2.image_size is None and g2.descriptors.shape == (3, 4)
    # Stamp helpers are exact to the nanosecond.
    t = seconds_to_stamp(12.000000001)
    assert (t.sec, t.nanosec) == (12, 1) and abs(stamp_to_seconds(t) - 12.000000001) < 1e-12


@pytest.mark.parametrize("dim", [256, 250])
def test_keypoints_frame_roundtrip_binary_descriptors(dim):
    rng = np.random.default_rng(dim)
    bits = rng.integers(0, 2, size=(40, dim)).astype(np.float32)
    f = Frame(camera_id="cam0", stamp=5.0, keypoints=rng.uniform(0, 100, (40, 2)), descriptors=bits)
    msg = _roundtrip(frame_to_keypoints(f, descriptor_name="orb", binary=True))
    assert msg.descriptor_type == Keypoints.DESCRIPTOR_BINARY and msg.descriptor_dim == dim
    assert len(msg.descriptors) == 0 and len(msg.descriptors_binary) == 40 * ((dim + 7) // 8)
    g = keypoints_to_frame(msg)
    assert g.descriptors.dtype == np.float32
    np.testing.assert_array_equal(g.descriptors, bits)
    # Same packing as OpenCV/np.packbits (MSB first).
    np.testing.assert_array_equal(np.frombuffer(msg.descriptors_binary, np.uint8).reshape(40, -1),
                                  np.packbits(bits.astype(np.uint8), axis=1))


def _good_msg(n=10, dim=8) -> Keypoints:
    rng = np.random.default_rng(0)
    return frame_to_keypoints(Frame(camera_id="cam0", stamp=1.0, keypoints=rng.uniform(0, 9, (n, 2)),
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
        keypoints_to_frame(msg, camera_id="cam0")
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
    assert stamp_to_seconds(msg.header.stamp) == pytest.approx(10.02)
    w = match_window_to_arrays(msg)
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


# ---------------------------------------------------------------------------------------
# DDS harness
# ---------------------------------------------------------------------------------------
def _domain_id() -> int:
    return random.SystemRandom().randint(1, 100)


def _diag_values(msg: DiagnosticArray, hardware_id: str):
    for st in msg.status:
        if st.hardware_id == hardware_id:
            return st, {kv.key: kv.value for kv in st.values}
    return None, {}


class MatcherHarness:
    """A MatcherNode and a test node (publishers of the cameras, subscribers of the output and
    of /diagnostics) on one executor of their own context."""

    def __init__(self, cameras=CAMS, **params) -> None:
        from gcn_match_ros.ros.matcher_node import MatcherNode

        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=_domain_id(), signal_handler_options=SignalHandlerOptions.NO)
        self.ns = f"/t{uuid.uuid4().hex[:10]}"
        params = {"cameras": list(cameras), "solver": TEST_SOLVER, "input_qos": "reliable",
                  "diagnostics_period": 0.2, "max_age": 3.0, **params}
        self.node = None
        try:
            self.matcher = MatcherNode(context=self.ctx, namespace=self.ns,
                                       parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
            self.node = rclpy.create_node("tester", context=self.ctx, namespace=self.ns)
        except BaseException:
            rclpy.try_shutdown(context=self.ctx)
            raise
        self.windows = []
        self.diagnostics = []
        self.node.create_subscription(MatchWindow, "matcher_node/matches", self.windows.append, RELIABLE)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, RELIABLE)
        self.pubs = {c: self.node.create_publisher(Keypoints, f"{c}/keypoints", RELIABLE) for c in cameras}
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.matcher)
        self.executor.add_node(self.node)
        self.fqn = self.matcher.get_fully_qualified_name()
        assert self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values())
                               and self.matcher._matches_pub.get_subscription_count() > 0), "discovery timed out"

    def _on_diag(self, msg):
        st, values = _diag_values(msg, self.fqn)
        if st is not None:
            self.diagnostics.append((st, values))

    def spin_until(self, cond, timeout: float = 10.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if cond():
                return True
            self.executor.spin_once(timeout_sec=0.01)
        return bool(cond())

    def publish(self, frame: Frame, **kw) -> None:
        self.pubs[frame.camera_id].publish(frame_to_keypoints(frame, **kw))

    def wait_windows(self, n: int, timeout: float = 15.0) -> list:
        assert self.spin_until(lambda: len(self.windows) >= n, timeout), \
            f"got {len(self.windows)} windows, expected {n}; diagnostics: {self.last_values()}"
        return self.windows

    def last_values(self) -> dict:
        return self.diagnostics[-1][1] if self.diagnostics else {}

    def wait_diag(self, cond, timeout: float = 10.0):
        """Wait for a /diagnostics report (published after now) whose values satisfy ``cond``."""
        start = len(self.diagnostics)
        ok = self.spin_until(lambda: any(cond(v) for _, v in self.diagnostics[start:]), timeout)
        assert ok, f"no diagnostics report satisfied the condition; last: {self.last_values()}"
        return next((s, v) for s, v in self.diagnostics[start:] if cond(v))

    def close(self) -> None:
        try:
            assert self.matcher.stop(), "inference worker did not stop"
            nodes = self.executor.get_nodes()
            self.executor.shutdown(timeout_sec=1.0)
            for n in nodes:
                n.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.ctx)


@pytest.fixture
def harness_factory():
    made = []

    def make(**kw):
        h = MatcherHarness(**kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


def _score_window(msg: MatchWindow, sent: dict):
    """P/R of a window against the gt of the frames sent (looked up by camera and stamp)."""
    w = match_window_to_arrays(msg)
    frames, gts = [], []
    for cam, st in zip(w.camera_ids, w.view_stamps):
        (f, gt), = [v for (c, t), v in sent.items() if c == cam and abs(t - st) < 1e-4]
        frames.append(f)
        gts.append(gt)
    problem = Problem(view_offsets=w.view_offsets, keypoints=np.concatenate([f.keypoints for f in frames]),
                      descriptors=np.concatenate([f.descriptors for f in frames]), gt_track=np.concatenate(gts))
    result = Result(track=w.track, pair_rows=w.pair_rows, pair_cols=w.pair_cols, pair_scores=w.pair_scores)
    return score_result(problem, result)


# ---------------------------------------------------------------------------------------
# Matcher node over DDS
# ---------------------------------------------------------------------------------------
def _solvers_under_test():
    out = ["nn"]
    if _gcn_model_available():
        out.append("gcn")
    if TEST_SOLVER not in out:
        out.append(TEST_SOLVER)
    return out


@pytest.mark.parametrize("solver", _solvers_under_test())
def test_matcher_windows_score_high_against_ground_truth(harness_factory, solver):
    from gcn_match_ros.ros.example_consumer import MatchConsumer

    h = harness_factory(solver=solver, dense_output=True)
    consumer = MatchConsumer(context=h.ctx, namespace=h.ns,
                             cli_args=["--ros-args", "-r", "matches:=matcher_node/matches"])
    h.executor.add_node(consumer)
    assert h.spin_until(lambda: h.matcher._matches_pub.get_subscription_count() >= 2)
    scene = PermutedScene(points=60, dim=128, noise=0.05, distractors=5, seed=7)
    sent = {}
    stamps = {}
    n_windows = 4
    for k in range(n_windows):
        t0 = time.time()
        for i, cam in enumerate(CAMS):
            f, gt = scene.frame(cam, t0 - 0.002 * i)
            sent[(cam, f.stamp)] = (f, gt)
            msg = frame_to_keypoints(f)
            stamps[(cam, k)] = (msg.header.stamp.sec, msg.header.stamp.nanosec)
            h.pubs[cam].publish(msg)
        h.wait_windows(k + 1)  # complete windows are emitted at once
        # MatchWindow carries the views' exact header stamps (to look up Keypoints messages).
        assert [(s.sec, s.nanosec) for s in h.windows[k].view_stamps] == [stamps[(c, k)] for c in CAMS]
    scores = [_score_window(m, sent) for m in h.windows]
    for m in h.windows:
        validate_match_window(m)
        assert list(m.camera_ids) == CAMS and m.method.startswith(solver)
        assert len(m.dense_scores) == (len(m.track)) ** 2
        assert 0.0 < m.latency_seconds < 5.0 and m.total_seconds >= m.solve_seconds > 0.0
    p = np.mean([s["P"] for s in scores])
    r = np.mean([s["R"] for s in scores])
    assert p > 0.9 and r > 0.8, f"{solver}: P={p:.3f} R={r:.3f}"
    assert h.spin_until(lambda: consumer.windows == n_windows) and consumer.malformed == 0
    assert len(consumer.last["tracks"]) == h.windows[-1].track_count and consumer.last["pairs"]
    _, values = h.wait_diag(lambda v: v.get("windows published") == str(n_windows))
    assert values["solver"].startswith(solver) and values["windows dropped total"] == "0"
    assert float(values["latency p95 [ms]"]) > 0 and values["frames received cam2"] == str(n_windows)


def test_matcher_counts_bad_input_and_keeps_running(harness_factory):
    h = harness_factory(solver="nn", max_keypoints=200)
    scene = PermutedScene(points=40, dim=128, seed=11)
    clock = iter(time.time() + 0.3 * k for k in range(100))  # increasing stamps, never stale
    sent = {}

    def good_window():
        t = next(clock)
        for cam in CAMS:
            f, gt = scene.frame(cam, t)
            sent[(cam, t)] = (f, gt)
            h.publish(f)

    good_window()
    h.wait_windows(1)

    def bad(cam="cam0", **changes):
        f, _ = scene.frame(cam, next(clock))
        msg = frame_to_keypoints(f)
        for k, v in changes.items():
            setattr(msg, k, v)
        h.pubs[cam].publish(msg)

    rng = np.random.default_rng(0)
    n = scene.points + scene.distractors
    bad(descriptor_dim=64, descriptors=array.array("f", rng.normal(size=n * 64).astype(np.float32).tobytes()))
    bad(keypoints=array.array("f", [1.0] * (2 * n - 2)))                                   # count mismatch
    bad(descriptors=array.array("f", np.full(n * 128, np.nan, np.float32).tobytes()))      # NaN
    bad(keypoints=array.array("f", np.full(2 * n, np.inf, np.float32).tobytes()))          # inf
    bad(count=0, keypoints=array.array("f"), descriptors=array.array("f"), scales=array.array("f"),
        orientations=array.array("f"))                                                    # empty frame
    bad(descriptor_type=5)                                                                 # unknown type
    bad(count=5_000_000)                                                                   # absurd count
    bad(camera_id="cam7")                                                                  # wrong camera
    f, _ = scene.frame("cam1", time.time() + 100.0)                                        # far future
    h.publish(f)
    f, _ = scene.frame("cam1", time.time() - 50.0)                                         # out of order
    h.publish(f)
    # Topics are not ordered against each other: let the bad frames be handled first.
    h.wait_diag(lambda v: v.get("frames dropped total") == "10")
    # A huge frame (6000 keypoints) is cut to max_keypoints and still matched.
    t = next(clock)
    big = Frame(camera_id="cam0", stamp=t, keypoints=rng.uniform(0, 600, (6000, 2)),
                descriptors=np.abs(rng.normal(size=(6000, 128))).astype(np.float32))
    h.publish(big)
    for cam in CAMS[1:]:
        h.publish(scene.frame(cam, t)[0])
    h.wait_windows(2)
    good_window()

    expected = {"frames dropped descriptor_dim": "1", "frames dropped count_mismatch": "1",
                "frames dropped non_finite": "2", "frames dropped empty": "1",
                "frames dropped descriptor_type": "1", "frames dropped too_large": "1",
                "frames dropped camera_mismatch": "1", "frames dropped future": "1",
                "frames dropped out_of_order": "1", "frames truncated": "1", "windows published": "3"}
    st, values = h.wait_diag(lambda v: all(v.get(k) == x for k, x in expected.items()))
    assert values["frames dropped total"] == "10" and values["windows dropped total"] == "0"
    assert len(h.windows) == 3
    for m in h.windows:
        validate_match_window(m)
    big_window = h.windows[1]
    assert np.diff(np.asarray(big_window.view_offsets)).tolist() == [200, n, n]
    assert _score_window(h.windows[2], sent)["P"] > 0.9
    assert h.matcher._worker.is_alive()


def test_matcher_silent_camera_windows_continue(harness_factory):
    h = harness_factory(solver="nn")
    scene = PermutedScene(points=30, dim=64, seed=5)
    base = time.time() - 0.5
    for k in range(5):  # cam2 never publishes; each new period settles the previous window
        for cam in CAMS[:2]:
            h.publish(scene.frame(cam, base + 0.2 * k)[0])
        h.wait_windows(k)  # one at a time: a burst would (correctly) supersede pending windows
    h.wait_windows(4)
    assert all(list(m.camera_ids) == ["cam0", "cam1"] for m in h.windows)
    st, values = h.wait_diag(lambda v: v.get("windows published") == "4")
    assert st.level == DiagnosticStatus.WARN and "cam2" in st.message
    assert values["frames received cam2"] == "0" and float(values["input rate cam2 [Hz]"]) == 0.0


class _GateSolver(Solver):
    """Test solver: blocks while ``armed`` until ``gate`` is set; fails on views of 13 keypoints."""

    name = "test_gate"
    armed = False
    gate = threading.Event()
    entered = threading.Event()

    def match(self, problem, graph):
        if type(self).armed:
            type(self).entered.set()
            type(self).gate.wait(10.0)
        if 13 in problem.view_sizes.tolist():
            raise RuntimeError("injected failure")
        return SoftMatches.from_graph(graph, values=graph.cosine), None


if _GateSolver.name not in available_solvers():
    register(_GateSolver)


def test_matcher_worker_drops_superseded_stale_and_survives_solver_errors(harness_factory):
    h = harness_factory(solver="test_gate", max_age=1.0)
    scene = PermutedScene(points=20, dim=32, distractors=0, seed=2)
    gate = _GateSolver
    gate.gate.clear()
    gate.entered.clear()
    gate.armed = True
    try:
        def window(t, points=None):
            for cam in CAMS:
                f, _ = scene.frame(cam, t)
                if points is not None and cam == "cam0":
                    f.keypoints, f.descriptors = f.keypoints[:points], f.descriptors[:points]
                    f.scales, f.orientations = f.scales[:points], f.orientations[:points]
                h.publish(f)

        t = time.time()
        window(t)            # taken by the worker, which blocks in the solver
        assert h.spin_until(gate.entered.is_set)
        window(t + 0.1)      # pending ...
        window(t + 0.2)      # ... replaced: superseded
        h.wait_diag(lambda v: v.get("windows dropped superseded") == "1")
        # Let the pending window grow older than max_age, then release the worker.
        assert h.spin_until(lambda: time.time() - (t + 0.2) > 1.05, timeout=5.0)
        gate.armed = False
        gate.gate.set()
        h.wait_diag(lambda v: v.get("windows dropped stale_window") == "1" and v.get("windows published") == "1")
        window(time.time(), points=13)   # the solver raises on this one
        h.wait_diag(lambda v: v.get("windows dropped solver_error") == "1")
        window(time.time())
        h.wait_windows(2)
        _, values = h.wait_diag(lambda v: v.get("windows published") == "2")
        assert values["windows dropped total"] == "3" and h.matcher._worker.is_alive()
        assert [round(stamp_to_seconds(m.header.stamp) - t, 1) for m in h.windows[:1]] == [0.0]
    finally:
        gate.armed = False
        gate.gate.set()


def test_matcher_rejects_invalid_parameter_changes(harness_factory):
    h = harness_factory(solver="nn")
    m = h.matcher
    res = m.set_parameters([Parameter("min_views", value=4)])       # more than the 3 cameras
    assert not res[0].successful and "min_views" in res[0].reason
    res = m.set_parameters([Parameter("score_threshold", value=1.5)])  # outside its range
    assert not res[0].successful
    res = m.set_parameters([Parameter("solver", value="spectral")])    # read-only
    assert not res[0].successful
    assert m.set_parameters([Parameter("sync_tolerance", value=0.02)])[0].successful
    assert m._assembler.config.sync_tolerance == 0.02


# ---------------------------------------------------------------------------------------
# Matcher node as a process: start-up failures, SIGTERM
# ---------------------------------------------------------------------------------------
def _node_env() -> dict:
    from gcn_match_ros.ros import use_large_shm

    env = dict(os.environ)
    use_large_shm(env)
    env["ROS_DOMAIN_ID"] = str(_domain_id())
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _matcher_cmd(*params: str, ns: str = "") -> list:
    cmd = [sys.executable, "-m", "gcn_match_ros.ros.matcher_node", "--ros-args"]
    for p in params:
        cmd += ["-p", p]
    if ns:
        cmd += ["-r", f"__ns:={ns}"]
    return cmd


def test_matcher_process_exits_nonzero_on_bad_startup(tmp_path):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"this is not a checkpoint" * 10)
    cases = {  # parameters -> what the log must say
        ("solver:=gcn", f"checkpoint:={tmp_path / 'missing.pt'}"): "missing.pt: no such checkpoint file",
        ("solver:=gcn", f"checkpoint:={corrupt}"): "corrupt.pt: not a readable checkpoint",
    }
    if not (REPO / "gcn_match_ros" / "solvers" / "gcn.py").is_file():
        cases = {("solver:=nope",): "unknown solver 'nope'"}
    procs = {args: subprocess.Popen(_matcher_cmd(*args), env=_node_env(), stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True, cwd=REPO)
             for args in cases}  # all at once: start-up (imports) dominates
    for args, proc in procs.items():
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 1, f"{args}: exit {proc.returncode}\n{out}"
        assert cases[args] in out and "cannot start" in out, f"{args}:\n{out}"
        assert "Traceback" not in out, out


@pytest.mark.parametrize("params,message", [
    ({"solver": "nope"}, "unknown solver 'nope'"),
    ({"solver": "nn:graph=nothing"}, "unknown graph 'nothing'"),
    ({"solver": "nn", "checkpoint": "/x.pt"}, "takes no checkpoint"),
    ({"solver": "nn", "min_views": 5}, "min_views"),
    ({"solver": "nn", "input_qos": "fast"}, "input_qos"),
    ({"solver": "nn", "cameras": ["cam0"]}, "at least 2"),
    ({"solver": "nn", "cameras": ["cam 0", "cam1"]}, "valid topic name"),
    ({"solver": "nn", "sync_tolerance": 1}, "sync_tolerance"),  # wrong type (int for a double)
])
def test_matcher_startup_errors_are_clear(params, message):
    from gcn_match_ros.ros.matcher_node import MatcherNode, StartupError

    ctx = Context()
    rclpy.init(context=ctx, domain_id=_domain_id(), signal_handler_options=SignalHandlerOptions.NO)
    try:
        with pytest.raises(StartupError, match=message):
            MatcherNode(context=ctx, namespace=f"/t{uuid.uuid4().hex[:10]}",
                        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
    finally:
        rclpy.try_shutdown(context=ctx)


def test_matcher_process_sigterm_clean_exit():
    """The node process, seen spinning (its /diagnostics arrive here), exits 0 on SIGTERM."""
    ns = f"/t{uuid.uuid4().hex[:10]}"
    env = _node_env()
    proc = subprocess.Popen(_matcher_cmd("solver:=nn", "diagnostics_period:=0.1", ns=ns), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]), signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = rclpy.create_node("tester", context=ctx)
        reports = []
        node.create_subscription(DiagnosticArray, "/diagnostics",
                                 lambda m: reports.extend(_diag_values(m, f"{ns}/matcher_node")[:1]), RELIABLE)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        end = time.monotonic() + 60
        while time.monotonic() < end and not any(r is not None for r in reports) and proc.poll() is None:
            ex.spin_once(timeout_sec=0.05)
        assert any(r is not None for r in reports), f"no diagnostics from {ns}/matcher_node"
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=20)
        ex.shutdown(timeout_sec=1.0)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
        if proc.poll() is None:
            proc.kill()
        out = proc.communicate(timeout=10)[0]
    assert rc == 0, out
    assert "Traceback" not in out, out


# ---------------------------------------------------------------------------------------
# Feature node
# ---------------------------------------------------------------------------------------
def _texture(h=240, w=320, seed=0) -> np.ndarray:
    import cv2

    rng = np.random.default_rng(seed)
    img = np.zeros((h, w), np.uint8)
    for _ in range(60):
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        cv2.circle(img, (x, y), int(rng.integers(3, 20)), int(rng.integers(60, 255)), -1)
        cv2.rectangle(img, (x, y), (x + int(rng.integers(5, 30)), y + int(rng.integers(5, 30))),
                      int(rng.integers(0, 200)), 2)
    return cv2.GaussianBlur(img, (3, 3), 0)


def _image_msg(img: np.ndarray, encoding: str, stamp: float) -> Image:
    msg = Image()
    msg.header.stamp = seconds_to_stamp(stamp)
    msg.header.frame_id = "cam0_optical_frame"
    msg.height, msg.width = img.shape[:2]
    msg.encoding = encoding
    msg.step = img.shape[1] * (1 if img.ndim == 2 else 3)
    msg.data = array.array("B", np.ascontiguousarray(img).tobytes())
    return msg


def test_feature_node_turns_images_into_keypoints():
    from gcn_match_ros.ros.feature_node import FeatureNode

    ctx = Context()
    rclpy.init(context=ctx, domain_id=_domain_id(), signal_handler_options=SignalHandlerOptions.NO)
    ns = f"/t{uuid.uuid4().hex[:10]}/cam0"
    try:
        fn = FeatureNode(context=ctx, namespace=ns, parameter_overrides=[
            Parameter("camera_id", value="cam0"), Parameter("max_features", value=300)])
        node = rclpy.create_node("tester", context=ctx, namespace=ns)
        got = []
        node.create_subscription(Keypoints, "keypoints", got.append, RELIABLE)
        pub = node.create_publisher(Image, "image", RELIABLE)
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(fn)
        ex.add_node(node)

        def spin_until(cond, timeout=10.0):
            end = time.monotonic() + timeout
            while time.monotonic() < end and not cond():
                ex.spin_once(timeout_sec=0.01)
            return cond()

        assert spin_until(lambda: pub.get_subscription_count() > 0 and fn._pub.get_subscription_count() > 0)
        img = _texture()
        pub.publish(_image_msg(img, "mono8", 100.5))
        assert spin_until(lambda: len(got) == 1)
        m = got[0]
        assert m.camera_id == "cam0" and m.descriptor_name == "sift" and m.descriptor_dim == 128
        assert m.count > 20 and stamp_to_seconds(m.header.stamp) == pytest.approx(100.5)
        assert (m.camera_info.width, m.camera_info.height) == (320, 240)
        f = keypoints_to_frame(m)
        assert f.descriptors.shape == (m.count, 128) and f.K is None
        assert np.all((f.keypoints >= 0) & (f.keypoints < [320, 240]))

        # Colour input: same keypoints from BGR and RGB of the same grey image.
        pub.publish(_image_msg(np.dstack([img] * 3), "rgb8", 101.0))
        assert spin_until(lambda: len(got) == 2)
        assert got[1].count == m.count

        # Bad images are counted, nothing is published for them.
        short = _image_msg(img, "mono8", 102.0)
        short.data = array.array("B", bytes(100))
        pub.publish(short)  # (one at a time: the node keeps only the newest image)
        assert spin_until(lambda: fn.bad_images["bad_size"] == 1)
        pub.publish(_image_msg(img, "yuv422", 102.5))
        assert spin_until(lambda: fn.bad_images["encoding"] == 1)

        # ORB at run time; an unknown detector is rejected.
        assert not fn.set_parameters([Parameter("detector", value="surf")])[0].successful
        assert fn.set_parameters([Parameter("detector", value="orb")])[0].successful
        pub.publish(_image_msg(np.dstack([img] * 3), "bgr8", 103.0))
        assert spin_until(lambda: len(got) == 3)
        o = got[2]
        assert o.descriptor_type == Keypoints.DESCRIPTOR_BINARY and o.descriptor_dim == 256
        assert keypoints_to_frame(o).descriptors.shape == (o.count, 256)
        assert fn.images_received == 5 and fn.keypoints_published == 3
        ex.shutdown(timeout_sec=1.0)
        fn.destroy_node()
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


@pytest.mark.skipif(not _gcn_model_available(), reason="shipped model missing")
def test_matcher_gcn_takes_orb_and_drops_descriptors_without_a_model(harness_factory):
    """With the shipped models the gcn node takes 128-D real-valued (SIFT) or 256-bit binary
    (ORB) frames; descriptors no model was trained for are counted drops, not a crash and
    not matched by the wrong model."""
    h = harness_factory(solver="gcn")
    clock = iter(time.time() + 0.3 * k for k in range(100))
    rng = np.random.default_rng(3)
    n = 50
    for dim in (64, 256):  # 256-D real-valued: a learned descriptor, not ORB bits
        odd = Frame(camera_id="cam0", stamp=next(clock), keypoints=rng.uniform(0, 600, (n, 2)),
                    descriptors=np.abs(rng.normal(size=(n, dim))).astype(np.float32))
        h.publish(odd)
    h.wait_diag(lambda v: v.get("frames dropped descriptor_kind") == "2")
    bits = rng.integers(0, 2, size=(n, 256))
    xy = rng.uniform(20, 620, size=(n, 2))
    t = next(clock)
    for cam in CAMS:
        perm = rng.permutation(n)
        flip = rng.random((n, 256)) < 0.03
        f = Frame(camera_id=cam, stamp=t, keypoints=(xy[perm] + rng.normal(scale=1.0, size=(n, 2))).astype(np.float32),
                  descriptors=(bits[perm] ^ flip).astype(np.float32))
        h.publish(f, descriptor_name="orb", binary=True)
    (m,) = h.wait_windows(1)
    validate_match_window(m)
    assert h.matcher._assembler.config.descriptor_dim == 256
