"""The matcher node (gcn_match_ros.ros.matcher_node) over real DDS.

Every test that talks DDS has its own rclpy context (gcn_match_ros.ros.testing.RosSession)
on a random ROS_DOMAIN_ID and its own node namespace (so even a domain shared with a
concurrent run never mixes topics); discovery is confined to this machine. Nothing sleeps a
fixed time: tests spin the executor until a condition holds or a timeout passes.

The matcher tests run with ``GCN_MATCH_TEST_SOLVER`` (default: ``gcn``, the shipped model);
the accuracy test runs nn and gcn (and that solver).
"""
from __future__ import annotations

import array
import os
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.parameter import Parameter

from gcn_match_msgs.msg import Keypoints, MatchWindow
from gcn_match_ros.metrics import score_result
from gcn_match_ros.problem import Problem, Result
from gcn_match_ros.ros.conversions import frame_to_keypoints, match_window_to_arrays, validate_match_window
from gcn_match_ros.ros.dds import use_large_shm
from gcn_match_ros.ros.example_consumer import MatchConsumer
from gcn_match_ros.ros.matcher_node import MatcherNode, StartupError
from gcn_match_ros.ros.parameters import MATCHER_PARAMETERS
from gcn_match_ros.ros.testing import RosSession, diagnostic_values
from gcn_match_ros.solvers import SoftMatches, Solver, available_solvers, register
from gcn_match_ros.stamps import seconds_to_ns, stamp_to_ns
from gcn_match_ros.windowing import Frame, WindowConfig

from conftest import PROCESS_CPUS, PermutedScene, domain_id, needs_two_cpus

REPO = Path(__file__).resolve().parents[1]
CAMS = ["cam0", "cam1", "cam2"]
TEST_SOLVER = os.environ.get("GCN_MATCH_TEST_SOLVER") or "gcn"


class MatcherHarness:
    """A MatcherNode and a test node (publishers of the cameras, subscribers of the output and
    of /diagnostics) on one executor of their own context."""

    def __init__(self, cameras=CAMS, **params) -> None:
        self.ns = f"/t{uuid.uuid4().hex[:10]}"
        self.session = RosSession("tester", namespace=self.ns, domain_id=domain_id())
        params = {"cameras": list(cameras), "solver": TEST_SOLVER, "input_qos": "reliable",
                  "diagnostics_period": 0.2, "max_age": 3.0, **params}
        try:
            self.matcher = self.session.add_node(MatcherNode(
                context=self.session.context, namespace=self.ns,
                parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))
        except BaseException:
            self.session.close()
            raise
        self.fqn = self.matcher.get_fully_qualified_name()
        self.windows = self.session.collect(MatchWindow, "matcher_node/matches")
        self.diagnostics = []
        self.session.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 50)
        self.pubs = {c: self.session.publisher(Keypoints, f"{c}/keypoints") for c in cameras}
        assert self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values())
                               and self.matcher._matches_pub.get_subscription_count() > 0), "discovery timed out"

    def _on_diag(self, msg):
        found = diagnostic_values(msg, self.fqn)
        if found is not None:
            self.diagnostics.append(found)

    def spin_until(self, cond, timeout: float = 10.0) -> bool:
        return self.session.spin_until(cond, timeout)

    def publish(self, frame: Frame) -> None:
        self.pubs[frame.camera_id].publish(frame_to_keypoints(frame))

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
        finally:
            self.session.close()


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
    for cam, st in zip(w.camera_ids, w.view_stamps_ns):
        f, gt = sent[(cam, int(st))]
        frames.append(f)
        gts.append(gt)
    problem = Problem(view_offsets=w.view_offsets, keypoints=np.concatenate([f.keypoints for f in frames]),
                      descriptors=np.concatenate([f.descriptors for f in frames]), gt_track=np.concatenate(gts))
    result = Result(track=w.track, pair_rows=w.pair_rows, pair_cols=w.pair_cols, pair_scores=w.pair_scores)
    return score_result(problem, result)


def test_parameters_are_declared_from_one_table(harness_factory):
    h = harness_factory(solver="nn")
    declared = {name: h.matcher.get_parameter(name).value for name in (p.name for p in MATCHER_PARAMETERS)}
    defaults = WindowConfig(cameras=tuple(CAMS))
    for name in ("sync_tolerance", "max_delay", "min_views", "max_keypoints", "descriptor_dim"):
        assert declared[name] == getattr(defaults, name), name  # the node's defaults are WindowConfig's
    assert declared["max_age"] == 3.0 and declared["solver"] == "nn"  # overridden by the harness


# ---------------------------------------------------------------------------------------
# Matching
# ---------------------------------------------------------------------------------------
def _solvers_under_test():
    return ["nn", "gcn"] + ([TEST_SOLVER] if TEST_SOLVER not in ("nn", "gcn") else [])


def test_matcher_reuses_the_rigs_models_and_answers_as_offline(harness_factory):
    """A fixed rig: the node fits each camera pair's model once and re-checks it afterwards
    (diagnostics count it), gives the scene's points landmark ids that persist from window to
    window, and solving the same windows offline as one stream (gcn_match_ros.stream.solve_stream)
    gives the node's tracks and landmark ids exactly."""
    from gcn_match_ros import solvers
    from gcn_match_ros.data import synthetic
    from gcn_match_ros.stream import solve_stream
    from gcn_match_ros.windowing import window_problem

    h = harness_factory(solver="gcn")
    scene = synthetic.random_scene_problem(synthetic.rome16k(3, n_points=200), rng=np.random.default_rng(9))
    sent = []
    for k in range(3):
        t0 = time.time()
        frames = []
        for v, cam in enumerate(CAMS):
            sl = scene.view_slice(v)
            frames.append(Frame(camera_id=cam, stamp_ns=int((t0 - 0.002 * v) * 1e9), keypoints=scene.keypoints[sl],
                                descriptors=scene.descriptors[sl], scales=scene.scales[sl],
                                orientations=scene.orientations[sl], K=scene.K[v], image_size=(640, 480),
                                frame_id=f"{cam}_optical_frame", descriptor_name="sift"))
        for f in frames:
            h.publish(f)
        sent.append(frames)
        h.wait_windows(k + 1)
    _, values = h.wait_diag(lambda v: int(v.get("rig models reused", 0)) > 0)
    assert int(values["rig models fitted"]) < 3 * 3  # three view pairs, three windows: not every one fitted
    offline = list(solve_stream(solvers.create("gcn"), [window_problem(frames) for frames in sent],
                                stamps_ns=[max(f.stamp_ns for f in frames) for frames in sent]))
    online = [match_window_to_arrays(msg) for msg in h.windows]
    for w, (result, landmarks) in zip(online, offline):
        np.testing.assert_array_equal(w.track, result.track)
        np.testing.assert_array_equal(w.landmark_ids, landmarks.ids)
        np.testing.assert_allclose(w.landmark_ages, landmarks.ages_s, atol=1e-6)
    # the same scene in every window: the tracked points keep their ids, and age
    first, last = online[0], online[-1]
    tracked = first.landmark_ids >= 0
    assert tracked.sum() > 50
    assert (last.landmark_ids[tracked] == first.landmark_ids[tracked]).mean() > 0.95
    assert np.all(last.landmark_ages[tracked & (last.landmark_ids == first.landmark_ids)] > 0)


@pytest.mark.parametrize("solver", _solvers_under_test())
def test_matcher_windows_score_high_against_ground_truth(harness_factory, solver):
    h = harness_factory(solver=solver, dense_output=True)
    consumer = h.session.add_node(MatchConsumer(context=h.session.context, namespace=h.ns,
                                                cli_args=["--ros-args", "-r", "matches:=matcher_node/matches"]))
    assert h.spin_until(lambda: h.matcher._matches_pub.get_subscription_count() >= 2)
    scene = PermutedScene(points=60, dim=128, noise=0.05, distractors=5, seed=7)
    sent = {}
    n_windows = 4
    for k in range(n_windows):
        t0 = time.time()
        stamps = []
        for i, cam in enumerate(CAMS):
            f, gt = scene.frame(cam, t0 - 0.002 * i)
            sent[(cam, f.stamp_ns)] = (f, gt)
            stamps.append(f.stamp_ns)
            h.publish(f)
        h.wait_windows(k + 1)  # complete windows are emitted at once
        # MatchWindow carries the views' exact header stamps (to look up Keypoints messages).
        assert [stamp_to_ns(s) for s in h.windows[k].view_stamps] == stamps
    scores = [_score_window(m, sent) for m in h.windows]
    for m in h.windows:
        validate_match_window(m)
        assert list(m.camera_ids) == CAMS and m.method.startswith(solver)
        assert len(m.dense_scores) == (len(m.track)) ** 2
        assert 0.0 < m.latency_seconds < 5.0 and m.total_seconds >= m.solve_seconds > 0.0
        assert m.build_seconds > 0.0
    p = np.mean([s["P"] for s in scores])
    r = np.mean([s["R"] for s in scores])
    assert p > 0.9 and r > 0.8, f"{solver}: P={p:.3f} R={r:.3f}"
    assert h.spin_until(lambda: consumer.windows == n_windows) and consumer.malformed == 0
    assert len(consumer.last["tracks"]) == h.windows[-1].track_count and consumer.last["pairs"]
    _, values = h.wait_diag(lambda v: v.get("windows published") == str(n_windows))
    assert values["solver"].startswith(solver) and values["windows dropped total"] == "0"
    assert float(values["latency p95 [ms]"]) > 0 and values["frames received cam2"] == str(n_windows)
    assert 0 < float(values["landmark association p50 [ms]"]) < float(values["compute p50 [ms]"])


def test_matcher_without_landmarks_publishes_tracks_and_no_ids(harness_factory):
    """landmarks:=false: the same windows, tracks as before, the landmark fields left empty
    and the tracker never used."""
    h = harness_factory(solver="nn", landmarks=False)
    scene = PermutedScene(points=60, dim=128, noise=0.05, distractors=5, seed=7)
    for k in range(2):
        t0 = time.time()
        for i, cam in enumerate(CAMS):
            h.publish(scene.frame(cam, t0 - 0.002 * i)[0])
        h.wait_windows(k + 1)
    for m in h.windows:
        validate_match_window(m)
        assert m.track_count > 30 and len(m.landmark_ids) == 0 and len(m.landmark_ages) == 0
    _, values = h.wait_diag(lambda v: v.get("windows published") == "2")
    assert values["landmarks live"] == "0" and values["landmarks born"] == "0"
    assert values["landmark association p50 [ms]"] == "nan"


def test_matcher_counts_bad_input_and_keeps_running(harness_factory):
    h = harness_factory(solver="nn", max_keypoints=200)
    scene = PermutedScene(points=40, dim=128, seed=11)
    clock = iter(time.time() + 0.3 * k for k in range(100))  # increasing stamps, never stale
    sent = {}

    def good_window():
        t = next(clock)
        for cam in CAMS:
            f, gt = scene.frame(cam, t)
            sent[(cam, f.stamp_ns)] = (f, gt)
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
    bad(keypoints=array.array("f", np.full(2 * n, 1e30, np.float32).tobytes()))           # finite, absurd
    bad(keypoints=array.array("f", np.full(2 * n, 5000.0, np.float32).tobytes()))         # outside the image
    bad(count=0, keypoints=array.array("f"), descriptors=array.array("f"), scales=array.array("f"),
        orientations=array.array("f"))                                                    # empty frame
    bad(descriptor_type=5)                                                                 # unknown type
    bad(count=5_000_000)                                                                   # absurd count
    bad(camera_id="cam7")                                                                  # wrong camera
    h.publish(scene.frame("cam1", time.time() + 100.0)[0])                                 # far future
    h.publish(scene.frame("cam1", time.time() - 50.0)[0])                                  # out of order
    # Topics are not ordered against each other: let the bad frames be handled first.
    h.wait_diag(lambda v: v.get("frames dropped total") == "12")
    # A huge frame (6000 keypoints) is cut to max_keypoints and still matched.
    t = next(clock)
    big = Frame(camera_id="cam0", stamp_ns=seconds_to_ns(t), keypoints=rng.uniform(0, 600, (6000, 2)),
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
                "frames dropped out_of_order": "1", "frames dropped out_of_range": "2", "frames truncated": "1",
                "windows published": "3"}
    st, values = h.wait_diag(lambda v: all(v.get(k) == x for k, x in expected.items()))
    assert values["frames dropped total"] == "12" and values["windows dropped total"] == "0"
    assert len(h.windows) == 3
    for m in h.windows:
        validate_match_window(m)
    big_window = h.windows[1]
    assert np.diff(np.asarray(big_window.view_offsets)).tolist() == [200, n, n]
    assert _score_window(h.windows[2], sent)["P"] > 0.9
    assert h.matcher._worker.is_alive()


def test_matcher_reports_whether_freed_memory_is_kept(harness_factory):
    """keep_freed_memory=false leaves glibc's thresholds alone, and /diagnostics says so (the
    default, set by the node process, is checked in test_matcher_process_sigterm_clean_exit)."""
    h = harness_factory(solver="nn", keep_freed_memory=False)
    h.wait_diag(lambda v: v.get("freed memory") == "given back (off)")


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

    @classmethod
    def arm(cls):
        """Block the next solve (after the node's warm-up) until :meth:`release`."""
        cls.gate.clear()
        cls.entered.clear()
        cls.armed = True

    @classmethod
    def release(cls):
        """Let every solve through from now on."""
        cls.armed = False
        cls.gate.set()

    def match(self, problem, graph, similarity):
        if type(self).armed:
            type(self).entered.set()
            type(self).gate.wait(10.0)
        if 13 in problem.view_sizes.tolist():
            raise RuntimeError("injected failure")
        return SoftMatches.from_graph(graph, values=graph.cosine), None


@pytest.fixture
def gate_solver():
    """_GateSolver registered (at test time, so collecting other test files never sees it);
    released whatever the test does, so a failing test never leaves a worker blocked."""
    if _GateSolver.name not in available_solvers():
        register(_GateSolver)
    try:
        yield _GateSolver
    finally:
        _GateSolver.release()


def test_matcher_worker_drops_superseded_stale_and_survives_solver_errors(harness_factory, gate_solver):
    h = harness_factory(solver="test_gate", max_age=1.0)
    scene = PermutedScene(points=20, dim=32, distractors=0, seed=2)
    gate = gate_solver
    gate.arm()

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
    gate.release()
    h.wait_diag(lambda v: v.get("windows dropped stale_window") == "1" and v.get("windows published") == "1")
    window(time.time(), points=13)   # the solver raises on this one
    h.wait_diag(lambda v: v.get("windows dropped solver_error") == "1")
    window(time.time())
    h.wait_windows(2)
    _, values = h.wait_diag(lambda v: v.get("windows published") == "2")
    assert values["windows dropped total"] == "3" and h.matcher._worker.is_alive()
    assert stamp_to_ns(h.windows[0].header.stamp) == seconds_to_ns(t)


def test_matcher_degrades_to_fewer_keypoints_when_behind_and_says_so(harness_factory, gate_solver):
    h = harness_factory(solver="test_gate", max_keypoints=40, degrade_min_keypoints=10, max_age=3.0)
    scene = PermutedScene(points=36, dim=32, distractors=0, seed=4)
    gate = gate_solver
    gate.arm()

    def window(t):
        for cam in CAMS:
            h.publish(scene.frame(cam, t)[0])

    t = time.time()
    window(t)                 # the worker blocks in the solver
    assert h.spin_until(gate.entered.is_set)
    for k in (1, 2, 3):       # two of these are superseded during that one solve: 40 -> 30, once
        window(t + 0.1 * k)
    h.wait_diag(lambda v: v.get("windows dropped superseded") == "2")
    gate.release()
    h.wait_windows(2)
    status, values = h.wait_diag(lambda v: v.get("windows published") == "2")
    assert values["keypoint budget"] == "30" and values["windows degraded"] == "1"
    assert status.level == DiagnosticStatus.WARN and "degraded under load" in status.message
    sizes = np.diff(np.asarray(h.windows[1].view_offsets))
    assert sizes.tolist() == [30, 30, 30]  # the best-scored 30 of each frame's 36


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


def test_matcher_gcn_takes_orb_and_drops_descriptors_without_a_model(harness_factory):
    """With the shipped models the gcn node takes 128-D real-valued (SIFT) or 256-bit binary
    (ORB) frames, by the type their messages declare; descriptors no model was trained for are
    counted drops, not a crash and not matched by the wrong model."""
    h = harness_factory(solver="gcn")
    clock = iter(time.time() + 0.3 * k for k in range(100))
    rng = np.random.default_rng(3)
    n = 50
    bits = rng.integers(0, 2, size=(n, 256))
    for dim, desc, binary in ((64, np.abs(rng.normal(size=(n, 64))), False),
                              (256, np.abs(rng.normal(size=(n, 256))), False),  # a learned descriptor
                              (256, bits, False)):  # bits declared as floats: still not ORB
        h.publish(Frame(camera_id="cam0", stamp_ns=seconds_to_ns(next(clock)), keypoints=rng.uniform(0, 600, (n, 2)),
                        descriptors=desc.astype(np.float32), binary=binary))
    h.wait_diag(lambda v: v.get("frames dropped descriptor_kind") == "3")
    xy = rng.uniform(20, 620, size=(n, 2))
    t = next(clock)
    for cam in CAMS:
        perm = rng.permutation(n)
        flip = rng.random((n, 256)) < 0.03
        h.publish(Frame(camera_id=cam, stamp_ns=seconds_to_ns(t),
                        keypoints=(xy[perm] + rng.normal(scale=1.0, size=(n, 2))).astype(np.float32),
                        descriptors=(bits[perm] ^ flip).astype(np.float32), binary=True, descriptor_name="orb"))
    (m,) = h.wait_windows(1)
    validate_match_window(m)
    assert h.matcher._assembler.descriptor_dim == 256


# ---------------------------------------------------------------------------------------
# Matcher node as a process: start-up failures, SIGTERM
# ---------------------------------------------------------------------------------------
def _node_env() -> dict:
    env = dict(os.environ)
    use_large_shm(env)
    env["ROS_DOMAIN_ID"] = str(domain_id())
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
    procs = {args: subprocess.Popen(_matcher_cmd(*args), env=_node_env(), stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True, cwd=REPO)
             for args in cases}  # all at once: start-up (imports) dominates
    for args, proc in procs.items():
        out, _ = proc.communicate(timeout=60)
        assert proc.returncode == 1, f"{args}: exit {proc.returncode}\n{out}"
        assert cases[args] in out and "cannot start" in out, f"{args}:\n{out}"
        assert "Traceback" not in out, out


@pytest.mark.parametrize("params,message", [
    ({"solver": "nope"}, "unknown method 'nope'"),
    ({"solver": "nn:graph=nothing"}, "unknown graph 'nothing'"),
    ({"solver": "nn", "checkpoint": "/x.pt"}, "takes no checkpoint"),
    ({"solver": "gcn:checkpoint=/a.pt", "checkpoint": "/b.pt"}, "given twice"),
    ({"solver": "nn", "min_views": 5}, "min_views"),
    ({"solver": "nn", "input_qos": "fast"}, "input_qos"),
    ({"solver": "nn", "cameras": ["cam0"]}, "at least 2"),
    ({"solver": "nn", "cameras": ["cam 0", "cam1"]}, "valid topic name"),
    ({"solver": "nn", "sync_tolerance": 1}, "sync_tolerance"),  # wrong type (int for a double)
    ({"solver": "nn", "cpu_affinity": 4095}, "cpu_affinity=4095: CPU 4095 is not one this process may use"),
])
def test_matcher_startup_errors_are_clear(params, message):
    with RosSession("tester", domain_id=domain_id()) as session:
        with pytest.raises(StartupError, match=message):
            MatcherNode(context=session.context, namespace=f"/t{uuid.uuid4().hex[:10]}",
                        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])


def test_matcher_process_sigterm_clean_exit():
    """The node process, seen spinning (its /diagnostics arrive here, saying it keeps freed memory
    for the next window: parameter keep_freed_memory's default), exits 0 on SIGTERM."""
    ns = f"/t{uuid.uuid4().hex[:10]}"
    env = _node_env()
    proc = subprocess.Popen(_matcher_cmd("solver:=nn", "diagnostics_period:=0.1", ns=ns), env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    try:
        with RosSession("tester", domain_id=int(env["ROS_DOMAIN_ID"])) as session:
            reports = session.collect(DiagnosticArray, "/diagnostics")
            seen = session.spin_until(lambda: proc.poll() is not None or any(
                (diagnostic_values(r, f"{ns}/matcher_node") or (None, {}))[1].get("freed memory")
                == "kept for the next window" for r in reports), timeout=60)
            assert seen and proc.poll() is None, f"no diagnostics (freed memory kept) from {ns}/matcher_node"
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
        out = proc.communicate(timeout=10)[0]
    assert rc == 0, out
    assert "Traceback" not in out, out


@needs_two_cpus
def test_matcher_process_solves_on_the_cpus_cpu_affinity_names():
    """cpu_affinity: the worker and the solver's second thread each on a CPU of their own, named
    in /diagnostics (a process of its own: pinning would outlive the test in this one)."""
    allowed = PROCESS_CPUS
    ns = f"/t{uuid.uuid4().hex[:10]}"
    env = _node_env()
    proc = subprocess.Popen(_matcher_cmd("solver:=nn", "diagnostics_period:=0.1", f"cpu_affinity:={allowed[-1]}",
                                         ns=ns), env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, cwd=REPO)
    try:
        with RosSession("tester", domain_id=int(env["ROS_DOMAIN_ID"])) as session:
            reports = session.collect(DiagnosticArray, "/diagnostics")
            want = f"{allowed[-1]}, {allowed[0]}"  # the next one after the last: wrapped around
            seen = session.spin_until(lambda: proc.poll() is not None or any(
                (diagnostic_values(r, f"{ns}/matcher_node") or (None, {}))[1].get("solve CPUs") == want
                for r in reports),
                timeout=60)
            assert seen and proc.poll() is None, f"no diagnostics naming CPUs {want} from {ns}/matcher_node"
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
        out = proc.communicate(timeout=10)[0]
    assert "Traceback" not in out, out


def test_the_warm_up_runs_the_one_plane_paths_too(monkeypatch):
    """The warm-up's planar window takes the paths of a window of one plane (near-duplicates
    ranked by the homographies), which its 3-D window never reaches: a fresh install would
    otherwise compile them on its first real planar window."""
    from gcn_match_ros import solvers
    from gcn_match_ros.edges import duplicates
    from gcn_match_ros.ros.matcher_node import _warmup_problem

    calls = []
    ranked = duplicates._raise_better_placed

    def counting(*args):
        calls.append(1)
        return ranked(*args)

    monkeypatch.setattr(duplicates, "_raise_better_placed", counting)
    solver = solvers.create("gcn")
    solver.solve(_warmup_problem(128))
    assert not calls
    solver.solve(_warmup_problem(128, planar=True))
    assert calls
