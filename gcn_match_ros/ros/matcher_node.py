"""matcher_node: joint multi-camera keypoint matching over synchronised windows.

Subscribes ``<camera>/keypoints`` (gcn_match_msgs/Keypoints, relative names: namespaces and
remapping work) for every camera in ``cameras``, groups frames into windows with
:class:`gcn_match_ros.windowing.WindowAssembler` (the trainer forms windows the same way),
solves each window with one solver (default ``gcn`` with the model shipped in the
package) and publishes ``~/matches`` (gcn_match_msgs/MatchWindow, reliable) and
``/diagnostics`` (diagnostic_msgs/DiagnosticArray, :mod:`.diagnostics`). Parameters:
:mod:`.parameters`.

Threading:
    - the executor thread runs the subscription callbacks: decode the message (no copy),
      hand it to the assembler (validation, per-camera buffering) and, when a window is
      complete, put it in a *single* pending slot. A window replacing one still pending
      is counted as dropped (``superseded``): the queue never grows, the newest data wins;
    - one inference worker thread takes the pending window, drops it if older than
      ``max_age`` (``stale_window``), solves it (``Solver.solve``: graph, matching,
      rounding, timed by stage), packs and validates the MatchWindow and publishes it;
    - the diagnostics timer runs on the executor thread.
    A solver exception for one window is logged (throttled), counted (``solver_error``)
    and the node goes on. A solver that cannot be created (unknown name, missing or
    corrupt checkpoint) stops the process at start-up with exit code 1.

Two nodes share this one implementation: :class:`MatcherNode` (``matcher_node``) is configured
and active from start-up; :class:`LifecycleMatcherNode` (``lifecycle_matcher_node``) is a
managed node — configure loads and warms up the model and validates the parameters (a failure
leaves it unconfigured, the reason logged), activate subscribes and publishes, deactivate stops
matching and keeps the model, cleanup / shutdown release everything.

Run::

    python -m gcn_match_ros.ros.matcher_node --ros-args -p cameras:='[cam0, cam1, cam2]' \\
        -p solver:=gcn -p checkpoint:=/path/model.pt
"""
from __future__ import annotations

import contextlib
import dataclasses
import itertools
import sys
import threading
import time
from typing import List, Optional, Tuple

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import SetParametersResult
from rclpy.lifecycle import LifecycleState, TransitionCallbackReturn
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from gcn_match_msgs.msg import Keypoints, MatchWindow

from .. import solvers
from ..allocator import keep_freed_memory
from ..bags.codec import frame_from_keypoints_msg
from ..data import synthetic
from ..descriptors import describe_descriptor_kind
from ..load_shedding import KeypointBudget
from ..problem import Problem
from ..rounding import compile_plain_merge
from ..stamps import ns_to_seconds
from ..stream import StreamState, solve_window
from ..threads import pinned_solve_threads, single_blas_thread, solve_cpus
from ..windowing import Frame, FrameError, WindowAssembler, WindowConfig, trim_frame, window_problem
from . import parameters
from .conversions import MatchWindowError, result_to_match_window, validate_match_window
from .diagnostics import MatcherStats
from .spin import run_node

__all__ = ["MatcherNode", "LifecycleMatcherNode", "StartupError", "create_solver", "main", "lifecycle_main"]

NODE_NAME = "matcher_node"
_THROTTLE_S = 5.0
#: /diagnostics' "solve CPUs" without cpu_affinity: the solver keeps its two threads on two CPUs
#: chosen anew for every window (threads.kept_apart)
PER_WINDOW = "chosen per window"
#: /diagnostics' "freed memory": keep_freed_memory set (True), refused (False, not glibc), off (None)
_FREED_MEMORY = {True: "kept for the next window", False: "given back (not glibc)", None: "given back (off)"}


class StartupError(RuntimeError):
    """The node cannot start as configured (the message says why); the process exits 1."""


def create_solver(spec: str, checkpoint: str = "", device: str = "cpu") -> solvers.Solver:
    """The solver of ``spec`` (``name`` or ``name:key=value,...``) with the node's ``checkpoint``
    (when not empty) and ``device`` parameters, for solvers that take such settings.

    Raises:
        StartupError: unknown solver, bad settings, a checkpoint for a solver without one, or a
            checkpoint that cannot be loaded.
    """
    try:
        name, settings = solvers.parse_method(spec)
        takes = solvers.settings_of(name)
    except Exception as exc:  # unknown name, malformed spec, a solver module that fails to import
        raise StartupError(f"parameter solver='{spec}': {type(exc).__name__}: {exc}") from None
    overrides = {}
    if checkpoint:
        if "checkpoint" not in takes:
            raise StartupError(f"parameter checkpoint='{checkpoint}' is set but solver '{name}' takes no checkpoint")
        overrides["checkpoint"] = checkpoint
    if "device" in takes and "device" not in settings:
        overrides["device"] = device
    try:
        return solvers.create(spec, **overrides)
    except Exception as exc:  # CheckpointError, ValueError of settings, torch device errors, ...
        raise StartupError(f"cannot create solver '{spec}'"
                           + (f" with checkpoint '{checkpoint}'" if checkpoint else "")
                           + f": {type(exc).__name__}: {exc}") from None


def _warmup_problem(dim: int, binary: bool = False, planar: bool = False) -> Problem:
    """Three views of a small synthetic 3-D scene (:func:`gcn_match_ros.data.synthetic.easy`:
    every view pair has a trusted non-planar model, so the geometric paths run), with ``dim``
    descriptors of the kind to warm up (binary: 0/1 bits); ``planar``: every point at one depth
    in front of a forward-moving camera, a window of one plane (its own compiled paths: one-plane
    windows, near-duplicates placed by the homographies)."""
    config = synthetic.easy(3, descriptor_kind="binary" if binary else "sift", descriptor_dim=dim, n_points=60)
    if planar:
        config = config.replace(layout="forward", depth_range=(5.0, 5.0))
    return synthetic.random_scene_problem(config, rng=0)


@dataclasses.dataclass
class _Job:
    frames: List[Frame]
    formed: float  # monotonic time the window was formed


def _dims_text(dims: Tuple[int, ...]) -> str:
    return " or ".join(str(d) for d in dims)


class _Matcher:
    """The matcher's whole behaviour, in life-cycle steps shared by :class:`MatcherNode` (all
    steps at construction) and :class:`LifecycleMatcherNode` (each step a transition).
    Mixed into an rclpy node class; parameters are declared by :meth:`_declare`."""

    def _declare(self) -> None:
        parameters.declare(self)
        self._worker: Optional[threading.Thread] = None
        self._subs: list = []
        self._solver = None
        self._assembler = None
        self.add_on_set_parameters_callback(self._on_set_parameters)

    # -- configure: validate parameters, load and warm up the solver ------------------------
    def _configure(self) -> None:
        """Raises StartupError (invalid parameters, a solver that cannot be created or run)."""
        p = parameters.values(self)
        cameras = [str(c) for c in p["cameras"]]
        if len(cameras) < 2:
            raise StartupError(f"parameter cameras needs at least 2 camera ids, got {cameras}")
        self._cameras = tuple(cameras)
        try:
            config = self._window_config({n: p[n] for n in parameters.WINDOW_PARAMETER_NAMES})
        except ValueError as exc:
            raise StartupError(f"invalid windowing parameters: {exc}") from None
        if p["input_qos"] not in parameters.INPUT_QOS:
            raise StartupError(f"parameter input_qos='{p['input_qos']}': must be one of "
                               f"{', '.join(parameters.INPUT_QOS)}")
        device = p["device"]
        if not (device == "cpu" or device == "cuda" or device.startswith("cuda:")):
            raise StartupError(f"parameter device='{device}': must be 'cpu', 'cuda' or 'cuda:<index>'")
        for cam in self._cameras:  # checked here (rcl's rule), so a lifecycle node fails in configure
            try:
                self.resolve_topic_name(f"{cam}/keypoints")
            except Exception as exc:
                raise StartupError(f"camera id '{cam}' does not make a valid topic name: {exc}") from None
        self._score_threshold = float(p["score_threshold"])
        self._dense_output = bool(p["dense_output"])
        self._landmarks = bool(p["landmarks"])
        self._input_qos = p["input_qos"]
        self._diagnostics_period = float(p["diagnostics_period"])
        self._cpu_affinity = int(p["cpu_affinity"])
        if self._cpu_affinity >= 0:
            try:
                solve_cpus(self._cpu_affinity)
            except ValueError as exc:
                raise StartupError(f"parameter cpu_affinity={self._cpu_affinity}: {exc}") from None
        self._solve_cpus = PER_WINDOW

        t0 = time.perf_counter()
        single_blas_thread()
        self._freed_memory = _FREED_MEMORY[keep_freed_memory() if p["keep_freed_memory"] else None]
        self._solver = create_solver(p["solver"], p["checkpoint"], device)
        # what the stream learns from earlier windows (the rig's two-view models, the landmarks);
        # the worker thread alone solves, in window order, as gcn_match_ros.stream.solve_stream
        # does offline
        self._stream = StreamState()
        self._method = self._solver.describe()
        self._solver_kinds = tuple((int(d), bool(b)) for d, b in self._solver.descriptor_kinds)
        self._solver_dims = tuple(sorted({d for d, _ in self._solver_kinds}))
        if self._solver_dims and config.descriptor_dim not in (0,) + self._solver_dims:
            raise StartupError(f"parameter descriptor_dim={config.descriptor_dim} but solver {self._method} "
                               f"takes {_dims_text(self._solver_dims)}-D descriptors")
        config = dataclasses.replace(config, descriptor_dim=self._required_dim(config.descriptor_dim))
        warm = self._warm_up(config.descriptor_dim)
        self.get_logger().info(f"solver {self._method} ready in {time.perf_counter() - t0:.2f} s ({warm})")

        self._lock = threading.Lock()  # assembler, stats, settings
        self._cv = threading.Condition(threading.Lock())  # pending slot
        self._assembler = WindowAssembler(config)
        self._budget = KeypointBudget(config.max_keypoints, int(p["degrade_min_keypoints"]))
        self._last_window_ns: Optional[int] = None
        self._stats = MatcherStats(self._cameras)
        self._pending: Optional[_Job] = None
        self._busy = False
        self._stopping = False

    # -- activate: publishers, subscriptions, diagnostics, the worker -----------------------
    def _activate(self) -> None:
        self._matches_pub = self.create_publisher(
            MatchWindow, "~/matches",
            QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        qos = qos_profile_sensor_data if self._input_qos == "sensor_data" else QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self._subs = [self.create_subscription(Keypoints, f"{cam}/keypoints",
                                               lambda msg, cam=cam: self._on_keypoints(msg, cam), qos)
                      for cam in self._cameras]
        self._diag_timer = self.create_timer(self._diagnostics_period, self._publish_diagnostics)
        with self._cv:
            self._stopping = False
        self._worker = threading.Thread(target=self._worker_loop, name="matcher-inference", daemon=True)
        self._worker.start()
        config = self._assembler.config
        self.get_logger().info(
            f"matching cameras {list(self._cameras)} ({self._input_qos} input: "
            f"{', '.join(s.topic_name for s in self._subs)}) -> {self._matches_pub.topic_name}; "
            f"sync_tolerance {config.sync_tolerance} s, max_delay {config.max_delay} s, "
            f"min_views {config.min_views}, max_age {config.max_age} s, max_keypoints {config.max_keypoints}")

    # -- deactivate: stop matching, keep the model ------------------------------------------
    def _deactivate(self) -> bool:
        """Stop input, the worker (after its current window) and the outputs; True if the
        worker has ended. The solver and its stream state stay loaded."""
        stopped = self.stop()
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []
        self.destroy_timer(self._diag_timer)
        self.destroy_publisher(self._matches_pub)
        self.destroy_publisher(self._diag_pub)
        return stopped

    # -- cleanup: release the model ------------------------------------------------------------
    def _cleanup(self) -> None:
        self._solver = None
        self._stream = None
        self._assembler = None

    @property
    def solver_loaded(self) -> bool:
        return self._solver is not None


    def _window_config(self, values: dict) -> WindowConfig:
        return WindowConfig(cameras=self._cameras, **values)

    def _required_dim(self, dim: int) -> int:
        """The parameter, or with 0 the solver's single descriptor dimension if it has one
        (else 0: the assembler takes the first frame's)."""
        return dim or (self._solver_dims[0] if len(self._solver_dims) == 1 else 0)

    def _warm_up(self, dim: int) -> str:
        """Two windows of a small stream of a 3-D scene and two of a plane, each on a throwaway
        stream state: first-call costs (model loads, compiled loops where numba cannot cache
        them or has not yet: a fresh install compiled the one-plane paths on its first Oxford
        window, ~0.6 s; the plain greedy merge, :func:`gcn_match_ros.rounding.compile_plain_merge`)
        leave the first real windows, and a solver that cannot run at all is found at start-up."""
        t = time.perf_counter()
        kinds = [k for k in self._solver_kinds if not dim or k[0] == dim] or [(dim or 128, False)]
        for (d, binary), planar in itertools.product(kinds, (False, True)):  # every model loads at start-up
            try:
                problem, state = _warmup_problem(d, binary, planar), StreamState()
                problem.camera_ids = tuple(f"warm-up{v}" for v in range(problem.n_views))
                for k in range(2):  # the second window also associates landmarks
                    solve_window(self._solver, problem, state, k * 100_000_000)
            except Exception as exc:
                raise StartupError(f"solver {self._method} fails on a {d}-D warm-up window: "
                                   f"{type(exc).__name__}: {exc}") from None
        compile_plain_merge()
        return f"warm-up {1e3 * (time.perf_counter() - t):.0f} ms"

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Validate (and apply) run-time changes; ranges and read-only are checked by rclpy."""
        changes = {p.name: p.value for p in params}
        if self._assembler is None:  # unconfigured: configure validates them
            return SetParametersResult(successful=True)
        window = {k: v for k, v in changes.items() if k in parameters.WINDOW_PARAMETER_NAMES}
        new_config = None
        if window:
            with self._lock:
                current = self._assembler.config
            values = {n: getattr(current, n) for n in parameters.WINDOW_PARAMETER_NAMES}
            values.update(window)
            if "descriptor_dim" in window:
                dim = int(window["descriptor_dim"])
                if self._solver_dims and dim not in (0,) + self._solver_dims:
                    return SetParametersResult(successful=False, reason=(
                        f"solver {self._method} takes {_dims_text(self._solver_dims)}-D descriptors"))
                values["descriptor_dim"] = self._required_dim(dim)
            try:
                new_config = self._window_config(values)
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        with self._lock:
            if new_config is not None:
                self._assembler.reconfigure(new_config)
                self._budget.reconfigure(new_config.max_keypoints)
            if "score_threshold" in changes:
                self._score_threshold = float(changes["score_threshold"])
            if "dense_output" in changes:
                self._dense_output = bool(changes["dense_output"])
        return SetParametersResult(successful=True)

    # -- input (executor thread) ----------------------------------------------------------
    def _now_ns(self) -> Optional[int]:
        """Node clock in nanoseconds; None while a simulated clock has not started."""
        ns = self.get_clock().now().nanoseconds
        return ns if ns > 0 else None

    def _on_keypoints(self, msg: Keypoints, camera: str) -> None:
        with self._lock:
            self._stats.frame_received(camera)
        try:
            frame = frame_from_keypoints_msg(msg, camera_id=camera)
        except FrameError as exc:
            with self._lock:
                self._stats.conversion_drops[exc.reason] += 1
            self.get_logger().warning(f"dropped a frame of {camera}: {exc} ({exc.reason})",
                                      throttle_duration_sec=_THROTTLE_S)
            return
        kind = (int(frame.descriptors.shape[1]), frame.binary)
        if self._solver_kinds and frame.count > 0 and kind not in self._solver_kinds:  # fixed at start-up
            with self._lock:
                self._stats.conversion_drops["descriptor_kind"] += 1
            self.get_logger().warning(
                f"dropped a frame of {camera}: {describe_descriptor_kind(kind)} descriptors, which solver "
                f"{self._method} has no model for (descriptor_kind)", throttle_duration_sec=_THROTTLE_S)
            return
        with self._lock:
            dim_before = self._assembler.descriptor_dim
            if frame.count > self._assembler.config.max_keypoints:
                self._stats.truncated += 1
            drops_before = sum(self._assembler.drops.values())
            windows = self._assembler.add(frame, now_ns=self._now_ns())
            dim_after = self._assembler.descriptor_dim
            dropped = sum(self._assembler.drops.values()) > drops_before
            reasons = dict(self._assembler.drops) if dropped else None
        if dim_before == 0 and dim_after:
            self.get_logger().info(f"descriptor dimension {dim_after} (from the first frame, {camera}); "
                                   f"frames of another dimension are dropped")
        if dropped:
            self.get_logger().warning(f"frames dropped so far: {reasons} (latest from {camera} at "
                                      f"{ns_to_seconds(frame.stamp_ns):.3f})", throttle_duration_sec=_THROTTLE_S)
        for frames in windows:
            self._submit(frames)

    def _submit(self, frames: List[Frame]) -> None:
        with self._cv:
            superseded = self._pending is not None
            self._pending = _Job(frames, time.monotonic())
            self._cv.notify()
        if superseded:
            self._drop_window("superseded")
            with self._lock:
                self._budget.behind()
            self.get_logger().warning("inference busy: a pending window was replaced by a newer one "
                                      "(superseded)", throttle_duration_sec=_THROTTLE_S)

    # -- inference worker -----------------------------------------------------------------
    def _worker_loop(self) -> None:
        # pinned (cpu_affinity) while the worker runs: the threads' CPUs and torch's thread count
        # are given back when it stops, for whatever else runs in this process
        with contextlib.ExitStack() as placement:
            if self._cpu_affinity >= 0:
                try:
                    cpus = placement.enter_context(pinned_solve_threads(self._cpu_affinity))
                    self._solve_cpus = ", ".join(str(c) for c in cpus)
                    self.get_logger().info(f"solving on CPUs {self._solve_cpus}")
                except (ValueError, OSError) as exc:  # the CPUs were taken away since configure
                    self.get_logger().error(f"cpu_affinity={self._cpu_affinity}: {exc}; the solve's CPUs "
                                            "are chosen per window")
            self._serve()
        self._solve_cpus = PER_WINDOW

    def _serve(self) -> None:
        """Solve the pending window, one after another, until stopped."""
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
                self._drop_window("internal_error")
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
        newest = max(f.stamp_ns for f in frames)
        with self._lock:
            max_age = self._assembler.config.max_age
            threshold, dense = self._score_threshold, self._dense_output
        now = self._now_ns()
        if now is not None and now - newest > max_age * 1e9:
            self._drop_window("stale_window")
            age = (now - newest) * 1e-9
            hint = ("; its stamps are far behind this node's clock: replaying a bag? use bag_play --restamp "
                    "(or use_sim_time with a /clock)") if age > 60.0 else ""
            self.get_logger().warning(f"dropped a window {age:.3f} s old (max_age {max_age} s){hint}",
                                      throttle_duration_sec=_THROTTLE_S)
            return
        t0 = time.perf_counter()
        with self._lock:
            budget = self._budget.current
        degraded = max(f.count for f in frames) > budget
        if degraded:  # under load: the best-scored keypoints of each frame (load_shedding)
            frames = [trim_frame(f, budget) for f in frames]
        try:
            problem = window_problem(frames)
        except FrameError as exc:
            self._drop_window(exc.reason)
            self.get_logger().warning(f"dropped a window: {exc}", throttle_duration_sec=_THROTTLE_S)
            return
        stacked = time.perf_counter() - t0
        try:
            result, landmarks = solve_window(self._solver, problem, self._stream, newest, self._landmarks)
        except Exception as exc:
            self._drop_window("solver_error")
            self.get_logger().error(f"solver {self._method} failed on a window of {problem.n_views} views, "
                                    f"{problem.n_keypoints} keypoints: {type(exc).__name__}: {exc}",
                                    throttle_duration_sec=_THROTTLE_S)
            return
        build = stacked + result.timings.get("graph", 0.0) + result.timings.get("similarity", 0.0)
        try:
            msg = result_to_match_window(frames, result, score_threshold=threshold, dense=dense,
                                         build_seconds=build, solve_seconds=stacked + result.seconds - build,
                                         method=result.method or self._method,
                                         landmark_ids=None if landmarks is None else landmarks.ids,
                                         landmark_ages=None if landmarks is None else landmarks.ages_s)
            validate_match_window(msg)
        except MatchWindowError as exc:
            self._drop_window("invalid_output")
            self.get_logger().error(f"solver {self._method} gave an inconsistent result ({exc.reason}): {exc}",
                                    throttle_duration_sec=_THROTTLE_S)
            return
        msg.total_seconds = time.perf_counter() - t0
        now = self._now_ns()
        msg.latency_seconds = (now - newest) * 1e-9 if now is not None else 0.0
        self._matches_pub.publish(msg)
        period = (newest - self._last_window_ns) * 1e-9 if self._last_window_ns is not None else 0.0
        self._last_window_ns = newest
        with self._lock:
            self._stats.window_published(float(msg.latency_seconds), float(msg.total_seconds),
                                         float("nan") if landmarks is None else landmarks.seconds)
            self._budget.solved(float(msg.total_seconds), period, degraded)

    # -- diagnostics (executor thread) ----------------------------------------------------
    def diagnostics(self) -> DiagnosticArray:
        """The current report (also published every ``diagnostics_period``)."""
        with self._cv:
            busy, pending = self._busy, self._pending is not None
        with self._lock:
            status = self._stats.report(
                f"{self.get_name()}: matcher", self.get_fully_qualified_name(), self._assembler.drops,
                self._assembler.descriptor_dim, busy, pending, stale_after=max(2.0 * self._diagnostics_period, 1.0),
                extra={"solver": self._method, "solve CPUs": self._solve_cpus, "freed memory": self._freed_memory,
                       "rig models reused": str(self._stream.rig.reused),
                       "rig models fitted": str(self._stream.rig.fitted),
                       "rig models invalidated": str(self._stream.rig.invalidated),
                       "rig pairs skipped (backing off)": str(self._stream.rig.skipped),
                       "rig pairs probed (no support, not fitted)": str(self._stream.rig.probed),
                       "landmarks live": str(len(self._stream.landmarks)),
                       "landmarks born": str(self._stream.landmarks.born),
                       "keypoint budget": str(self._budget.current),
                       "windows degraded": str(self._budget.degraded_windows)},
                warnings=[f"degraded under load: at most {self._budget.current} keypoints per view"]
                if self._budget.degraded else [])
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self.get_clock().now().to_msg()
        return arr

    def _publish_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics())

    # -- shutdown -------------------------------------------------------------------------
    def stop(self, timeout: float = 10.0) -> bool:
        """Stop the worker (after the window it is computing); True if it has ended."""
        if self._worker is None:
            return True
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


class MatcherNode(_Matcher, Node):
    """See the module docstring: configured and active from construction. ``**kwargs`` go to
    :class:`rclpy.node.Node` (``context``, ``parameter_overrides``, ``namespace``, ...).

    Raises:
        StartupError: invalid parameters or a solver that cannot be created.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        try:
            self._declare()
            self._configure()
            self._activate()
        except StartupError:
            self.destroy_node()
            raise
        except Exception as exc:  # e.g. a parameter override of the wrong type
            self.destroy_node()
            raise StartupError(f"{type(exc).__name__}: {exc}") from None


class LifecycleMatcherNode(_Matcher, LifecycleNode):
    """The matcher as a managed node (the life cycle of heavy perception nodes):

    - configure: validate the parameters, load and warm up the model; an error leaves the node
      unconfigured and logs the reason;
    - activate: create the publishers and subscriptions, start matching;
    - deactivate: stop matching (subscriptions and outputs gone) and keep the model;
    - cleanup / shutdown: release everything.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self._declare()

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except Exception as exc:
            self._solver = None
            self.get_logger().error(f"configure failed: {type(exc).__name__}: {exc}")
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._activate()  # its inputs were validated in configure
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if not self._deactivate():
            self.get_logger().warning("inference worker still busy after deactivate")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._cleanup()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._worker is not None and self._worker.is_alive():
            self._deactivate()
        self._cleanup()
        return TransitionCallbackReturn.SUCCESS


def main(args=None) -> int:
    """Console script ``matcher_node``; returns the exit status (1: could not start).

    SIGINT / SIGTERM (rclpy's handlers) end the spin with ExternalShutdownException; the
    worker finishes the window it is computing and is joined, then the process exits 0.
    """
    def stop_worker(node: "MatcherNode") -> None:
        if not node.stop():
            rclpy.logging.get_logger(NODE_NAME).warning("inference worker still busy at shutdown")

    return run_node(MatcherNode, NODE_NAME, args, start_errors=(StartupError,), on_shutdown=stop_worker)



def lifecycle_main(args=None) -> int:
    """Console script ``lifecycle_matcher_node``: the managed matcher, unconfigured until a
    lifecycle manager (or ``ros2 lifecycle set``) configures and activates it."""
    def release(node: "LifecycleMatcherNode") -> None:
        if node._worker is not None and not node.stop():
            rclpy.logging.get_logger(NODE_NAME).warning("inference worker still busy at shutdown")

    return run_node(LifecycleMatcherNode, NODE_NAME, args, start_errors=(StartupError,), on_shutdown=release)


if __name__ == "__main__":
    sys.exit(main())
