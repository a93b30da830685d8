"""matcher_node: joint multi-camera keypoint matching over synchronised windows.

Subscribes ``<camera>/keypoints`` (gcn_match_msgs/Keypoints, relative names: namespaces and
remapping work) for every camera in ``cameras``, groups frames into windows with
:class:`gcn_match_ros.windowing.WindowAssembler` (the trainer forms windows the same way),
solves each window with one solver (default ``gcn`` with the model shipped in the
package) and publishes ``~/matches`` (gcn_match_msgs/MatchWindow, reliable) and
``/diagnostics`` (diagnostic_msgs/DiagnosticArray).

Threading:
    - the executor thread runs the subscription callbacks: convert the message (no copy),
      hand it to the assembler (validation, per-camera buffering) and, when a window is
      complete, put it in a *single* pending slot. A window replacing one still pending
      is counted as dropped (``superseded``): the queue never grows, the newest data wins;
    - one inference worker thread takes the pending window, drops it if older than
      ``max_age`` (``stale_window``), builds the problem and graph, runs the solver,
      packs and validates the MatchWindow and publishes it;
    - the diagnostics timer runs on the executor thread.
    A solver exception for one window is logged (throttled), counted (``solver_error``)
    and the node goes on. A solver that cannot be created (unknown name, missing or
    corrupt checkpoint) stops the process at start-up with exit code 1.

Run::

    python -m gcn_match_ros.ros.matcher_node --ros-args -p cameras:='[cam0, cam1, cam2]' \\
        -p solver:=gcn -p checkpoint:=/path/model.pt
"""
from __future__ import annotations

import collections
import dataclasses
import importlib
import math
import sys
import threading
import time
from typing import Dict, List, Optional, Tuple

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType,
                                SetParametersResult)
from rclpy.node import Node

from .spin import run_node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from gcn_match_msgs.msg import Keypoints, MatchWindow

from .. import solvers as _solvers
from ..descriptors import describe_descriptor_kind, descriptor_kind
from ..graph import build_graph
from ..problem import Problem
from ..solvers import available_solvers, get_solver, parse_method
from ..windowing import Frame, FrameError, WindowAssembler, WindowConfig, window_problem
from .conversions import (MatchWindowError, keypoints_to_frame, result_to_match_window,
                          validate_match_window)

__all__ = ["MatcherNode", "StartupError", "create_solver", "solver_descriptor_kinds", "main", "INPUT_QOS"]

NODE_NAME = "matcher_node"
#: Accepted values of the ``input_qos`` parameter.
INPUT_QOS = ("sensor_data", "reliable")
#: Latency / compute percentiles in the diagnostics cover this many recent seconds.
STATS_HORIZON_S = 10.0
#: Parameters that shape windowing (may change at run time; checked by building a WindowConfig).
_WINDOW_PARAMS = ("sync_tolerance", "max_delay", "min_views", "max_age", "max_keypoints", "descriptor_dim")
_THROTTLE_S = 5.0


class StartupError(RuntimeError):
    """The node cannot start as configured (the message says why); the process exits 1."""


# ---------------------------------------------------------------------------------------
# Solver creation
# ---------------------------------------------------------------------------------------
def _solver_class(name: str):
    """Registered solver class of ``name``; imports ``gcn_match_ros.solvers.<name>`` if it is
    not registered yet (a solver module that the package does not import by default)."""
    if name not in available_solvers() and name.isidentifier():
        try:
            importlib.import_module(f"{_solvers.__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{_solvers.__name__}.{name}":
                raise  # the solver module exists but a dependency of it is missing
    registry = getattr(_solvers.base, "_REGISTRY", {})
    return registry.get(name)


def create_solver(spec: str, checkpoint: str = "", device: str = "cpu"):
    """The solver of ``spec`` (``name`` or ``name:key=value,...``).

    ``checkpoint`` (when not empty) and ``device`` are passed as settings to solvers whose
    configuration has such fields (the ``gcn`` solver); ``checkpoint=''`` leaves the
    solver's default (the model shipped in the package).

    Raises:
        StartupError: unknown solver, bad settings, or a checkpoint that cannot be loaded.
    """
    try:
        name, settings = parse_method(spec)
    except ValueError as exc:
        raise StartupError(f"parameter solver='{spec}': {exc}") from None
    try:
        cls = _solver_class(name)
    except Exception as exc:  # the solver's module failed to import
        raise StartupError(f"solver '{name}' cannot be imported: {type(exc).__name__}: {exc}") from None
    if cls is None:
        raise StartupError(f"unknown solver '{name}'; available: {', '.join(available_solvers())}")
    fields = {f.name for f in dataclasses.fields(cls.Config)}
    extra = {}
    if checkpoint:
        if "checkpoint" not in fields:
            raise StartupError(f"parameter checkpoint='{checkpoint}' is set but solver '{name}' takes no checkpoint")
        if "checkpoint" in settings and settings["checkpoint"] != checkpoint:
            raise StartupError(f"checkpoint given twice: parameter '{checkpoint}' and solver setting "
                               f"'{settings['checkpoint']}'")
        extra["checkpoint"] = checkpoint
    if "device" in fields and "device" not in settings:
        extra["device"] = device
    try:
        return get_solver(spec, **extra)
    except Exception as exc:  # CheckpointError, ValueError of settings, torch device errors, ...
        raise StartupError(f"cannot create solver '{spec}'"
                           + (f" with checkpoint '{checkpoint}'" if checkpoint else "")
                           + f": {type(exc).__name__}: {exc}") from None


def solver_descriptor_kinds(solver) -> Tuple[Tuple[int, bool], ...]:
    """(dimension, binary) of the descriptors a solver takes (a learned model's input; the
    ``gcn`` solver with the shipped models: one per model); () when any works."""
    kinds = getattr(solver, "descriptor_kinds", None)
    return tuple((int(d), bool(b)) for d, b in kinds) if kinds else ()


def _dims_text(dims: Tuple[int, ...]) -> str:
    return " or ".join(str(d) for d in dims)


def _warmup_problem(dim: int, binary: bool = False, views: int = 3, points: int = 40, seed: int = 0) -> Problem:
    """Small permuted-views problem (views see the same points in random order); binary:
    0/1 descriptors with a few flipped bits per view."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 2, size=(points, dim)) if binary else np.abs(rng.normal(size=(points, dim)))
    kps, desc = [], []
    for _ in range(views):
        perm = rng.permutation(points)
        if binary:
            desc.append((base[perm] ^ (rng.random((points, dim)) < 0.03)).astype(np.float32))
        else:
            desc.append(base[perm] + 0.05 * rng.normal(size=(points, dim)))
        kps.append(rng.uniform(0, 640, size=(points, 2)))
    return Problem(view_offsets=np.arange(views + 1) * points, keypoints=np.concatenate(kps),
                   descriptors=np.concatenate(desc))


# ---------------------------------------------------------------------------------------
# Statistics shared by the callbacks, the worker and the diagnostics timer
# ---------------------------------------------------------------------------------------
class _Stats:
    def __init__(self, cameras) -> None:
        self.received = collections.Counter({c: 0 for c in cameras})
        self.last_received: Dict[str, float] = {}
        self.conversion_drops: collections.Counter = collections.Counter()
        self.window_drops: collections.Counter = collections.Counter()
        self.truncated = 0
        self.published = 0
        self.recent = collections.deque()  # (monotonic, latency s, compute s) of published windows
        # Values at the previous diagnostics report, for rates.
        self.prev_time = time.monotonic()
        self.prev_received = collections.Counter(self.received)
        self.prev_published = 0
        self.prev_drops = 0


@dataclasses.dataclass
class _Job:
    frames: List[Frame]
    formed: float  # monotonic time the window was formed


def _descriptor(description: str, *, read_only: bool = False, type_=None, int_range=None,
                float_range=None, constraints: str = "") -> ParameterDescriptor:
    d = ParameterDescriptor(description=description, read_only=read_only, additional_constraints=constraints)
    if type_ is not None:
        d.type = type_
    if int_range is not None:
        d.integer_range = [IntegerRange(from_value=int_range[0], to_value=int_range[1], step=1)]
    if float_range is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(float_range[0]),
                                                     to_value=float(float_range[1]), step=0.0)]
    return d


def _percentile(values, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def _fmt(value: float, scale: float = 1.0, digits: int = 1) -> str:
    return "nan" if not math.isfinite(value) else f"{value * scale:.{digits}f}"


class MatcherNode(Node):
    """See the module docstring. ``**kwargs`` go to :class:`rclpy.node.Node` (``context``,
    ``parameter_overrides``, ``namespace``, ...).

    Raises:
        StartupError: invalid parameters or a solver that cannot be created.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        try:
            self._setup()
        except StartupError:
            self.destroy_node()
            raise
        except Exception as exc:  # e.g. a parameter override of the wrong type
            self.destroy_node()
            raise StartupError(f"{type(exc).__name__}: {exc}") from None

    # -- set-up -------------------------------------------------------------------------
    def _setup(self) -> None:
        self._declare_parameters()
        gp = self.get_parameter
        cameras = [str(c) for c in gp("cameras").value]
        if len(cameras) < 2:
            raise StartupError(f"parameter cameras needs at least 2 camera ids, got {cameras}")
        self._cameras = tuple(cameras)
        try:
            config = self._window_config_from({n: gp(n).value for n in _WINDOW_PARAMS})
        except ValueError as exc:
            raise StartupError(f"invalid windowing parameters: {exc}") from None
        input_qos = gp("input_qos").value
        if input_qos not in INPUT_QOS:
            raise StartupError(f"parameter input_qos='{input_qos}': must be one of {', '.join(INPUT_QOS)}")
        device = gp("device").value
        if not (device == "cpu" or device == "cuda" or device.startswith("cuda:")):
            raise StartupError(f"parameter device='{device}': must be 'cpu', 'cuda' or 'cuda:<index>'")
        self._score_threshold = float(gp("score_threshold").value)
        self._dense_output = bool(gp("dense_output").value)
        self._auto_dim = config.descriptor_dim == 0

        spec = gp("solver").value
        t0 = time.perf_counter()
        self._solver = create_solver(spec, gp("checkpoint").value, device)
        self._method = self._solver.describe()
        self._solver_kinds = solver_descriptor_kinds(self._solver)
        self._solver_dims = solver_dims = tuple(sorted({d for d, _ in self._solver_kinds}))
        if solver_dims and config.descriptor_dim not in (0,) + solver_dims:
            raise StartupError(f"parameter descriptor_dim={config.descriptor_dim} but solver {self._method} "
                               f"takes {_dims_text(solver_dims)}-D descriptors")
        if len(solver_dims) == 1:
            config = dataclasses.replace(config, descriptor_dim=solver_dims[0])
            self._auto_dim = False
        warm = self._warm_up(config.descriptor_dim)
        self.get_logger().info(f"solver {self._method} ready in {time.perf_counter() - t0:.2f} s ({warm})")

        self._lock = threading.Lock()  # assembler, stats, settings
        self._cv = threading.Condition(threading.Lock())  # pending slot
        self._assembler = WindowAssembler(config)
        self._stats = _Stats(self._cameras)
        # Exact header stamps of recent frames, by (camera, float stamp), for MatchWindow.view_stamps.
        self._stamps: "collections.OrderedDict" = collections.OrderedDict()
        self._pending: Optional[_Job] = None
        self._busy = False
        self._stopping = False

        self._matches_pub = self.create_publisher(
            MatchWindow, "~/matches",
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        qos = qos_profile_sensor_data if input_qos == "sensor_data" else QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self._subs = []
        for cam in self._cameras:
            try:
                self._subs.append(self.create_subscription(
                    Keypoints, f"{cam}/keypoints", lambda msg, cam=cam: self._on_keypoints(msg, cam), qos))
            except Exception as exc:  # invalid topic name
                raise StartupError(f"camera id '{cam}' does not make a valid topic name: {exc}") from None
        self._diag_timer = self.create_timer(gp("diagnostics_period").value, self._publish_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._worker = threading.Thread(target=self._worker_loop, name="matcher-inference", daemon=True)
        self._worker.start()
        self.get_logger().info(
            f"matching cameras {list(self._cameras)} ({input_qos} input: "
            f"{', '.join(s.topic_name for s in self._subs)}) -> {self._matches_pub.topic_name}; "
            f"sync_tolerance {config.sync_tolerance} s, max_delay {config.max_delay} s, "
            f"min_views {config.min_views}, max_age {config.max_age} s, max_keypoints {config.max_keypoints}")

    def _declare_parameters(self) -> None:
        STR, DBL = ParameterType.PARAMETER_STRING, ParameterType.PARAMETER_DOUBLE
        self.declare_parameter("cameras", ["cam0", "cam1", "cam2"], _descriptor(
            "Camera ids, in window order; subscribes <camera>/keypoints for each.", read_only=True,
            type_=ParameterType.PARAMETER_STRING_ARRAY, constraints="at least 2 distinct ids"))
        self.declare_parameter("sync_tolerance", 0.05, _descriptor(
            "Max image-stamp difference of the views of one window [s].", type_=DBL, float_range=(0.0, 10.0)))
        self.declare_parameter("max_delay", 0.1, _descriptor(
            "How much later (stamp time) than the other cameras a camera's frame may arrive and still "
            "join its window [s]; only delays windows that miss a camera.", type_=DBL, float_range=(0.0, 10.0)))
        self.declare_parameter("min_views", 2, _descriptor(
            "Fewest views a window may have.", int_range=(2, 64), constraints="<= number of cameras"))
        self.declare_parameter("max_age", 1.0, _descriptor(
            "Frames further than this behind the newest stamp, and windows older than this when the "
            "worker takes them, are dropped [s].", type_=DBL, float_range=(0.001, 3600.0)))
        self.declare_parameter("max_keypoints", 1024, _descriptor(
            "Frames with more keypoints keep the best-scored (else first) ones.", int_range=(1, 100000)))
        self.declare_parameter("descriptor_dim", 0, _descriptor(
            "Required descriptor dimension (floats or bits); 0: the first frame's.", int_range=(0, 4096)))
        names = sorted(set(available_solvers()) | {"gcn"})
        self.declare_parameter("solver", "gcn", _descriptor(
            f"Matching method, 'name' or 'name:key=value,...'; one of {', '.join(names)}.",
            read_only=True, type_=STR))
        self.declare_parameter("checkpoint", "", _descriptor(
            "GCN checkpoint file; empty: the model shipped in the package.", read_only=True, type_=STR))
        self.declare_parameter("device", "cpu", _descriptor(
            "Torch device of the gcn solver: cpu, cuda or cuda:<index>.", read_only=True, type_=STR))
        self.declare_parameter("score_threshold", 0.1, _descriptor(
            "Pairs scoring above it are listed in MatchWindow.pair_*.", type_=DBL, float_range=(0.0, 1.0)))
        self.declare_parameter("dense_output", False, _descriptor(
            "Also publish the dense N x N score matrix (windows up to 4096 keypoints)."))
        self.declare_parameter("input_qos", "sensor_data", _descriptor(
            "QoS of the keypoint subscriptions: sensor_data (best effort, depth 5) or reliable (depth 10).",
            read_only=True, type_=STR, constraints="sensor_data | reliable"))
        self.declare_parameter("diagnostics_period", 1.0, _descriptor(
            "Period of /diagnostics reports [s].", read_only=True, type_=DBL, float_range=(0.05, 60.0)))

    def _window_config_from(self, values: dict) -> WindowConfig:
        return WindowConfig(cameras=self._cameras, sync_tolerance=float(values["sync_tolerance"]),
                            max_delay=float(values["max_delay"]), min_views=int(values["min_views"]),
                            max_age=float(values["max_age"]), max_keypoints=int(values["max_keypoints"]),
                            descriptor_dim=int(values["descriptor_dim"]))

    def _warm_up(self, dim: int) -> str:
        """One solve on a small problem: first-call costs leave the first real window, and a
        solver that cannot run at all is found at start-up."""
        t = time.perf_counter()
        kinds = [k for k in self._solver_kinds if not dim or k[0] == dim] or [(dim or 128, False)]
        for d, binary in kinds:  # every model loads at start-up
            try:
                self._solver.solve(_warmup_problem(d, binary))
            except Exception as exc:
                raise StartupError(f"solver {self._method} fails on a {d}-D warm-up window: "
                                   f"{type(exc).__name__}: {exc}") from None
        return f"warm-up {1e3 * (time.perf_counter() - t):.0f} ms"

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Validate (and apply) run-time changes; ranges and read-only are checked by rclpy."""
        changes = {p.name: p.value for p in params}
        window = {k: v for k, v in changes.items() if k in _WINDOW_PARAMS}
        new_config = None
        with self._lock:
            current, auto = self._assembler.config, self._auto_dim
        if window:
            values = {n: getattr(current, n) for n in _WINDOW_PARAMS}
            values.update(window)
            if "descriptor_dim" in window:
                dim = int(window["descriptor_dim"])
                if self._solver_dims and dim not in (0,) + self._solver_dims:
                    return SetParametersResult(successful=False, reason=(
                        f"solver {self._method} takes {_dims_text(self._solver_dims)}-D descriptors"))
                # 0: the solver's single dimension, else the next frame's
                values["descriptor_dim"] = dim or (self._solver_dims[0] if len(self._solver_dims) == 1 else 0)
                auto = values["descriptor_dim"] == 0
            try:
                new_config = self._window_config_from(values)
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        with self._lock:
            if new_config is not None:
                self._assembler.config, self._auto_dim = new_config, auto
            if "score_threshold" in changes:
                self._score_threshold = float(changes["score_threshold"])
            if "dense_output" in changes:
                self._dense_output = bool(changes["dense_output"])
        return SetParametersResult(successful=True)

    # -- input (executor thread) ----------------------------------------------------------
    def _now(self) -> Optional[float]:
        """Node clock in seconds; None while a simulated clock has not started."""
        ns = self.get_clock().now().nanoseconds
        return ns * 1e-9 if ns > 0 else None

    def _on_keypoints(self, msg: Keypoints, camera: str) -> None:
        arrival = time.monotonic()
        with self._lock:
            self._stats.received[camera] += 1
            self._stats.last_received[camera] = arrival
        try:
            frame = keypoints_to_frame(msg, camera_id=camera)
        except FrameError as exc:
            with self._lock:
                self._stats.conversion_drops[exc.reason] += 1
            self.get_logger().warning(f"dropped a frame of {camera}: {exc} ({exc.reason})",
                                      throttle_duration_sec=_THROTTLE_S)
            return
        if self._solver_kinds and frame.count > 0:  # fixed at start-up: checked outside the lock
            kind = descriptor_kind(frame.descriptors)
            if kind not in self._solver_kinds:
                with self._lock:
                    self._stats.conversion_drops["descriptor_kind"] += 1
                self.get_logger().warning(
                    f"dropped a frame of {camera}: {describe_descriptor_kind(kind)} "
                    f"descriptors, which solver {self._method} has no model for (descriptor_kind)",
                    throttle_duration_sec=_THROTTLE_S)
                return
        with self._lock:
            cfg = self._assembler.config
            if self._auto_dim and cfg.descriptor_dim == 0 and frame.count > 0:
                cfg = dataclasses.replace(cfg, descriptor_dim=int(frame.descriptors.shape[1]))
                self._assembler.config = cfg
                self.get_logger().info(f"descriptor dimension {cfg.descriptor_dim} (from the first frame, "
                                       f"{camera}); frames of another dimension are dropped")
            if frame.count > cfg.max_keypoints:
                self._stats.truncated += 1
            self._stamps[(camera, frame.stamp)] = msg.header.stamp
            while len(self._stamps) > 2 * cfg.buffer_size * len(self._cameras):
                self._stamps.popitem(last=False)
            drops_before = sum(self._assembler.drops.values())
            windows = self._assembler.add(frame, now=self._now())
            dropped = sum(self._assembler.drops.values()) > drops_before
            reasons = dict(self._assembler.drops) if dropped else None
        if dropped:
            self.get_logger().warning(f"frames dropped so far: {reasons} (latest from {camera} at "
                                      f"{frame.stamp:.3f})", throttle_duration_sec=_THROTTLE_S)
        for frames in windows:
            self._submit(frames)

    def _submit(self, frames: List[Frame]) -> None:
        with self._cv:
            superseded = self._pending is not None
            self._pending = _Job(frames, time.monotonic())
            self._cv.notify()
        if superseded:
            with self._lock:
                self._stats.window_drops["superseded"] += 1
            self.get_logger().warning("inference busy: a pending window was replaced by a newer one "
                                      "(superseded)", throttle_duration_sec=_THROTTLE_S)

    # -- inference worker -----------------------------------------------------------------
    def _worker_loop(self) -> None:
        while True:
            with self._cv:
                while self._pending is None and not self._stopping:
                    self._cv.wait()
                if self._stopping:
                    return
                job, self._pending = self._pending, None
                self._busy = True
            try:
                self._process(job)
            except Exception as exc:  # never let the worker die
                with self._lock:
                    self._stats.window_drops["internal_error"] += 1
                self.get_logger().error(f"window processing failed: {type(exc).__name__}: {exc}",
                                        throttle_duration_sec=_THROTTLE_S)
            finally:
                with self._cv:
                    self._busy = False

    def _drop_window(self, reason: str) -> None:
        with self._lock:
            self._stats.window_drops[reason] += 1

    def _process(self, job: _Job) -> None:
        frames = job.frames
        newest = max(f.stamp for f in frames)
        with self._lock:
            max_age = self._assembler.config.max_age
            threshold, dense = self._score_threshold, self._dense_output
            stamps = [self._stamps.get((f.camera_id, f.stamp)) for f in frames]
        now = self._now()
        if now is not None and now - newest > max_age:
            self._drop_window("stale_window")
            hint = ("; its stamps are far behind this node's clock: replaying a bag? use bag_play --restamp "
                    "(or use_sim_time with a /clock)") if now - newest > 60.0 else ""
            self.get_logger().warning(f"dropped a window {now - newest:.3f} s old (max_age {max_age} s){hint}",
                                      throttle_duration_sec=_THROTTLE_S)
            return
        t0 = time.perf_counter()
        try:
            problem = window_problem(frames)
        except FrameError as exc:
            self._drop_window(exc.reason)
            self.get_logger().warning(f"dropped a window: {exc}", throttle_duration_sec=_THROTTLE_S)
            return
        try:
            graph = build_graph(problem, self._solver.graph_config)
            t1 = time.perf_counter()
            result = self._solver.solve(problem, graph=graph)
        except Exception as exc:
            self._drop_window("solver_error")
            self.get_logger().error(f"solver {self._method} failed on a window of {problem.n_views} views, "
                                    f"{problem.n_keypoints} keypoints: {type(exc).__name__}: {exc}",
                                    throttle_duration_sec=_THROTTLE_S)
            return
        t2 = time.perf_counter()
        try:
            msg = result_to_match_window(frames, result, score_threshold=threshold, dense=dense,
                                         build_seconds=t1 - t0, solve_seconds=t2 - t1,
                                         method=result.method or self._method, view_stamps=stamps)
            validate_match_window(msg)
        except MatchWindowError as exc:
            self._drop_window("invalid_output")
            self.get_logger().error(f"solver {self._method} gave an inconsistent result ({exc.reason}): {exc}",
                                    throttle_duration_sec=_THROTTLE_S)
            return
        msg.total_seconds = time.perf_counter() - t0
        now = self._now()
        msg.latency_seconds = (now - newest) if now is not None else 0.0
        self._matches_pub.publish(msg)
        with self._lock:
            st = self._stats
            st.published += 1
            st.recent.append((time.monotonic(), float(msg.latency_seconds), float(msg.total_seconds)))

    # -- diagnostics (executor thread) ----------------------------------------------------
    def diagnostics(self) -> DiagnosticArray:
        """The current report (also published every ``diagnostics_period``)."""
        mono = time.monotonic()
        with self._lock:
            st = self._stats
            while st.recent and st.recent[0][0] < mono - STATS_HORIZON_S:
                st.recent.popleft()
            lat = [r[1] for r in st.recent]
            comp = [r[2] for r in st.recent]
            elapsed = max(mono - st.prev_time, 1e-6)
            rates = {c: (st.received[c] - st.prev_received[c]) / elapsed for c in self._cameras}
            received = dict(st.received)
            silent = {c: (mono - st.last_received[c]) if c in st.last_received else None for c in self._cameras}
            frame_drops = collections.Counter(self._assembler.drops) + st.conversion_drops
            window_drops = collections.Counter(st.window_drops)
            total_drops = sum(frame_drops.values()) + sum(window_drops.values())
            new_drops = total_drops - st.prev_drops
            win_rate = (st.published - st.prev_published) / elapsed
            published, truncated = st.published, st.truncated
            st.prev_time, st.prev_received = mono, collections.Counter(st.received)
            st.prev_published, st.prev_drops = st.published, total_drops
            cfg = self._assembler.config
        with self._cv:
            busy, pending = self._busy, self._pending is not None

        stale_after = max(2.0 * self.get_parameter("diagnostics_period").value, 1.0)
        quiet = [c for c in self._cameras if silent[c] is None or silent[c] > stale_after]
        problems = []
        if new_drops:
            problems.append(f"{new_drops} drops since the last report")
        if quiet:
            problems.append(f"no input from {', '.join(quiet)}")
        level = DiagnosticStatus.WARN if problems else DiagnosticStatus.OK
        message = "; ".join(problems) or "ok"
        values = {
            "solver": self._method,
            "cameras": ",".join(self._cameras),
            "windows/s": _fmt(win_rate, digits=2),
            "windows published": str(published),
            "latency p50 [ms]": _fmt(_percentile(lat, 50), 1e3),
            "latency p95 [ms]": _fmt(_percentile(lat, 95), 1e3),
            "latency max [ms]": _fmt(max(lat) if lat else float("nan"), 1e3),
            "compute p50 [ms]": _fmt(_percentile(comp, 50), 1e3),
            "compute p95 [ms]": _fmt(_percentile(comp, 95), 1e3),
            "worker": "busy" if busy else "idle",
            "window pending": str(pending),
            "descriptor dim": str(cfg.descriptor_dim),
            "frames truncated": str(truncated),
            "frames dropped total": str(sum(frame_drops.values())),
            "windows dropped total": str(sum(window_drops.values())),
        }
        for cam in self._cameras:
            values[f"input rate {cam} [Hz]"] = _fmt(rates[cam], digits=2)
            values[f"frames received {cam}"] = str(received.get(cam, 0))
        for reason, n in sorted(frame_drops.items()):
            values[f"frames dropped {reason}"] = str(n)
        for reason, n in sorted(window_drops.items()):
            values[f"windows dropped {reason}"] = str(n)
        status = DiagnosticStatus(level=level, name=f"{self.get_name()}: matcher", message=message,
                                  hardware_id=self.get_fully_qualified_name(),
                                  values=[KeyValue(key=k, value=v) for k, v in values.items()])
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self.get_clock().now().to_msg()
        return arr

    def _publish_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics())

    # -- shutdown -------------------------------------------------------------------------
    def stop(self, timeout: float = 10.0) -> bool:
        """Stop the worker (after the window it is computing); True if it has ended."""
        with self._cv:
            self._stopping = True
            self._pending = None
            self._cv.notify_all()
        self._worker.join(timeout)
        return not self._worker.is_alive()

    def destroy_node(self) -> None:
        if getattr(self, "_worker", None) is not None and self._worker.is_alive():
            self.stop()
        super().destroy_node()


def main(args=None) -> int:
    """Console script ``matcher_node``; returns the exit status (1: could not start).

    SIGINT / SIGTERM (rclpy's handlers) end the spin with ExternalShutdownException; the
    worker finishes the window it is computing and is joined, then the process exits 0.
    """
    def stop_worker(node: "MatcherNode") -> None:
        if not node.stop():
            rclpy.logging.get_logger(NODE_NAME).warning("inference worker still busy at shutdown")

    return run_node(MatcherNode, NODE_NAME, args, start_errors=(StartupError,), on_shutdown=stop_worker)


if __name__ == "__main__":
    sys.exit(main())
