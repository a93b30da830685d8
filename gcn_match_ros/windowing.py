"""Group camera frames into matching windows — the same way online (node) and offline (trainer).

A *window* holds at most one frame per camera, all within ``sync_tolerance`` seconds of
each other. Windows are decided by image stamps alone (integer nanoseconds, as the
messages carry them), never by arrival time, so replaying a bag into the node and reading
the same bag in the trainer give identical windows.

Policy (:class:`WindowAssembler`):
- frames are validated (:func:`validate_frame`); bad ones are dropped and counted by reason;
- per camera, frames must arrive in stamp order (older ones: ``out_of_order``) and not lie
  far in the future of the caller's clock (``future``); buffers are bounded (``overflow``);
- the window is anchored at the oldest buffered frame. It is emitted as soon as every
  camera has a frame within the tolerance, or — when some camera is late or silent — once
  a frame newer than anchor + tolerance + ``max_delay`` has arrived (``max_delay`` is how
  much later than the other cameras' frames a camera's frame may still arrive). It needs
  ``min_views`` frames, else its frames are dropped (``incomplete``). A silent camera
  therefore never stops the others;
- frames older than ``max_age`` behind the newest stamp are dropped (``stale``);
- ``descriptor_dim`` 0 takes the dimension of the first frame (:attr:`WindowAssembler.descriptor_dim`);
- frames over ``max_keypoints`` keep the rows :func:`kept_rows` chooses.

:class:`WindowConfig` is the one owner of these settings and of their defaults: the matcher
node declares its parameters from it (:func:`window_parameters`) and reads bags with it.
"""
from __future__ import annotations

import collections
import dataclasses
from typing import Deque, Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .problem import FormatError, Problem, descriptor_range_fault, intrinsics_fault, keypoint_range_fault
from .stamps import duration_ns

__all__ = ["Frame", "FrameError", "WindowConfig", "WindowParameter", "window_parameters", "WindowAssembler", "trim_frame",
           "validate_frame", "kept_rows", "window_problem"]


class FrameError(ValueError):
    """A frame that cannot be matched; ``reason`` is a short counter key."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclasses.dataclass
class Frame:
    """Keypoints of one camera image.

    Attributes:
        camera_id: the camera; stamp_ns: the image stamp, integer nanoseconds.
        binary: the descriptors are bits (unpacked to 0/1 columns), as the message's
            ``descriptor_type`` said; descriptor_name: e.g. ``"sift"``, ``"orb"``.

    Shapes:
        keypoints: (N, 2) pixel x, y.  descriptors: (N, D).
        scales, orientations, scores: (N,) or None.
        K: (3, 3) or None (uncalibrated).  image_size: (width, height) or None.
        R, t: world->camera pose (3, 3), (3,) or None (only bags with poses have it).
    """

    camera_id: str
    stamp_ns: int
    keypoints: np.ndarray
    descriptors: np.ndarray
    frame_id: str = ""
    scales: Optional[np.ndarray] = None
    orientations: Optional[np.ndarray] = None
    scores: Optional[np.ndarray] = None
    K: Optional[np.ndarray] = None
    image_size: Optional[tuple] = None
    R: Optional[np.ndarray] = None
    t: Optional[np.ndarray] = None
    binary: bool = False
    descriptor_name: str = ""

    @property
    def count(self) -> int:
        return int(np.shape(self.keypoints)[0]) if np.ndim(self.keypoints) == 2 else -1


def _parameter(default, doc: str, low=None, high=None, constraints: str = ""):
    """A WindowConfig field that is also a matcher-node parameter (read by :func:`window_parameters`)."""
    return dataclasses.field(default=default, metadata={"doc": doc, "range": (low, high), "constraints": constraints})


@dataclasses.dataclass(frozen=True)
class WindowConfig:
    """How frames form windows; the defaults are the matcher node's.

    Attributes:
        cameras: camera ids in window order (a window lists its views in this order).
        sync_tolerance: max stamp difference to the window's anchor, seconds.
        min_views: fewest views a window may have.
        max_delay: how much later (in stamp time) than other cameras' frames a camera's frame
            may arrive and still join its window, seconds; only delays windows missing a camera.
        max_age: frames further than this behind the newest stamp are dropped, seconds.
        max_keypoints: frames with more keypoints keep the best-scored (else first) ones.
        descriptor_dim: required descriptor dimension (0: the first frame's).
        max_future: frames stamped further than this ahead of the caller's clock are dropped, seconds.
        buffer_size: frames buffered per camera.
    """

    cameras: tuple
    sync_tolerance: float = _parameter(0.05, "Max image-stamp difference of the views of one window [s].",
                                       0.0, 10.0)
    max_delay: float = _parameter(0.1, "How much later (stamp time) than the other cameras a camera's frame "
                                       "may arrive and still join its window [s]; only delays windows that miss "
                                       "a camera.", 0.0, 10.0)
    min_views: int = _parameter(2, "Fewest views a window may have.", 2, 64, "<= number of cameras")
    max_age: float = _parameter(1.0, "Frames further than this behind the newest stamp, and windows older than "
                                     "this when the worker takes them, are dropped [s].", 0.001, 3600.0)
    max_keypoints: int = _parameter(1024, "Frames with more keypoints keep the best-scored (else first) ones.",
                                    1, 100000)
    descriptor_dim: int = _parameter(0, "Required descriptor dimension (floats or bits); 0: the first frame's.",
                                     0, 4096)
    max_future: float = 5.0
    buffer_size: int = 8

    def __post_init__(self) -> None:
        if len(self.cameras) < 1 or len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras must be distinct and non-empty, got {list(self.cameras)}")
        if not 2 <= self.min_views <= max(len(self.cameras), 2):
            raise ValueError(f"min_views must be in [2, {len(self.cameras)}], got {self.min_views}")
        if self.sync_tolerance < 0 or self.max_delay < 0 or self.max_age <= 0 or self.max_keypoints < 1 or self.buffer_size < 1:
            raise ValueError("sync_tolerance >= 0, max_delay >= 0, max_age > 0, max_keypoints >= 1, buffer_size >= 1 required")


class WindowParameter(NamedTuple):
    """A matcher-node parameter that is a :class:`WindowConfig` field."""

    name: str
    default: object
    doc: str
    low: object
    high: object
    constraints: str


def window_parameters() -> Tuple[WindowParameter, ...]:
    """The :class:`WindowConfig` fields the matcher node declares as parameters, with their
    defaults, descriptions and ranges, in declaration order."""
    return tuple(WindowParameter(f.name, f.default, f.metadata["doc"], *f.metadata["range"], f.metadata["constraints"])
                 for f in dataclasses.fields(WindowConfig) if "doc" in f.metadata)


def _optional(arr, n: int, name: str, shape_tail=()) -> Optional[np.ndarray]:
    if arr is None or np.size(arr) == 0:
        return None
    a = np.asarray(arr, dtype=np.float64)
    if a.shape != (n, *shape_tail):
        raise FrameError("bad_shape", f"{name}: expected shape {(n, *shape_tail)}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise FrameError("non_finite", f"{name}: contains NaN or inf")
    return a


def kept_rows(n: int, scores: Optional[np.ndarray], max_keypoints: int) -> np.ndarray:
    """The rows of an n-keypoint frame that a window keeps, in their original order: all of
    them, or the ``max_keypoints`` best-scored (without scores, the first) ones.

    Shapes: scores (n,) or None -> (min(n, max_keypoints),) int64.
    """
    if n <= max_keypoints:
        return np.arange(n)
    if scores is not None and np.size(scores):
        return np.sort(np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")[:max_keypoints])
    return np.arange(max_keypoints)


def _check_ranges(kp: np.ndarray, desc: np.ndarray, image_size) -> None:
    """Raise ``out_of_range`` for keypoints or descriptors no camera produces (validate_frame)."""
    size = image_size if image_size is not None and len(image_size) == 2 else None
    fault = keypoint_range_fault(kp, size) or descriptor_range_fault(desc)
    if fault:
        raise FrameError("out_of_range", fault)


def validate_frame(frame: Frame, config: Optional[WindowConfig] = None, descriptor_dim: int = 0) -> Frame:
    """Validate a frame and return a cleaned copy (float32 arrays, the :func:`kept_rows` of
    ``config.max_keypoints``).

    Args:
        descriptor_dim: required descriptor dimension (0: any).

    Raises:
        FrameError: with reason ``bad_shape``, ``count_mismatch``, ``non_finite``, ``empty``,
            ``descriptor_dim``, ``bad_intrinsics`` (K not a finite (3, 3) pinhole matrix,
            :func:`.problem.intrinsics_fault`; all zeros, ROS's "uncalibrated", drops K) or
            ``out_of_range`` (a keypoint outside the image when its size is known, else beyond
            :data:`.problem.MAX_ABS_PIXEL`; a descriptor value beyond
            :data:`.problem.MAX_ABS_DESCRIPTOR`: finite but meaningless, and the similarity of
            such values overflows to NaN; :func:`.problem.keypoint_range_fault`).
    """
    kp = np.asarray(frame.keypoints, dtype=np.float64)
    desc = np.asarray(frame.descriptors, dtype=np.float64)
    if kp.ndim != 2 or kp.shape[1] != 2:
        raise FrameError("bad_shape", f"keypoints: expected shape (N, 2), got {kp.shape}")
    n = kp.shape[0]
    if n == 0:
        raise FrameError("empty", "frame has no keypoints")
    if desc.ndim != 2 or desc.shape[0] != n:
        raise FrameError("count_mismatch", f"descriptors: expected shape ({n}, D), got {desc.shape}")
    if descriptor_dim and desc.shape[1] != descriptor_dim:
        raise FrameError("descriptor_dim", f"descriptors: dimension {desc.shape[1]}, expected {descriptor_dim}")
    if not (np.all(np.isfinite(kp)) and np.all(np.isfinite(desc))):
        raise FrameError("non_finite", "keypoints or descriptors contain NaN or inf")
    _check_ranges(kp, desc, frame.image_size)
    scales = _optional(frame.scales, n, "scales")
    orient = _optional(frame.orientations, n, "orientations")
    scores = _optional(frame.scores, n, "scores")
    K = frame.K
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise FrameError("bad_intrinsics", f"K: expected a finite (3, 3) matrix, got shape {K.shape}")
        if not K.any():
            K = None  # all-zero CameraInfo.k: uncalibrated
        elif fault := intrinsics_fault(K):
            raise FrameError("bad_intrinsics", f"K: {fault}")
    clean = dataclasses.replace(frame, keypoints=kp, descriptors=desc, scales=scales, orientations=orient,
                                scores=scores, K=K)
    if config is not None:
        clean = trim_frame(clean, config.max_keypoints)
    f32 = (lambda a: None if a is None else a.astype(np.float32))  # noqa: E731
    return dataclasses.replace(clean, keypoints=f32(clean.keypoints), descriptors=f32(clean.descriptors),
                               scales=f32(clean.scales), orientations=f32(clean.orientations), scores=f32(clean.scores))


def trim_frame(frame: Frame, max_keypoints: int) -> Frame:
    """The frame with only the keypoints a window keeps (:func:`kept_rows`): all of them, or the
    ``max_keypoints`` best-scored ones (per-keypoint fields cut alike)."""
    if frame.count <= max_keypoints:
        return frame
    keep = kept_rows(frame.count, frame.scores, max_keypoints)
    sub = (lambda a: None if a is None else a[keep])  # noqa: E731
    return dataclasses.replace(frame, keypoints=frame.keypoints[keep], descriptors=frame.descriptors[keep],
                               scales=sub(frame.scales), orientations=sub(frame.orientations),
                               scores=sub(frame.scores))


def window_problem(frames: Sequence[Frame], name: str = "") -> Problem:
    """Stack the frames of a window into a :class:`Problem` (views in the given order).

    Optional per-keypoint and per-view fields are kept only when every frame has them.
    """
    if not frames:
        raise FrameError("empty", "window has no frames")
    dims = {f.descriptors.shape[1] for f in frames}
    if len(dims) != 1:
        raise FrameError("descriptor_dim", f"descriptor dimensions differ within the window: {sorted(dims)}")
    sizes = [f.count for f in frames]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

    def stack(attr, per_view=False):
        vals = [getattr(f, attr) for f in frames]
        if any(v is None for v in vals):
            return None
        return np.stack(vals) if per_view else np.concatenate(vals)

    image_size = stack("image_size", per_view=True)
    try:
        return Problem(view_offsets=offsets, keypoints=stack("keypoints"), descriptors=stack("descriptors"),
                       scales=stack("scales"), orientations=stack("orientations"),
                       K=stack("K", per_view=True), R=stack("R", per_view=True), t=stack("t", per_view=True),
                       image_size=image_size, name=name, camera_ids=[f.camera_id for f in frames])
    except FormatError as exc:
        raise FrameError("bad_shape", str(exc)) from None


class WindowAssembler:
    """Buffers frames per camera and emits windows (see the module docstring for the policy).

    Attributes:
        descriptor_dim: the descriptor dimension frames must have: ``config.descriptor_dim``,
            or with 0 the first frame's (0 until a frame came).
        drops, received: counters by reason / by camera; windows_emitted.
    """

    def __init__(self, config: WindowConfig) -> None:
        self._buffers: Dict[str, Deque[Frame]] = {c: collections.deque() for c in config.cameras}
        self._last_stamp: Dict[str, int] = {}
        self._newest: Optional[int] = None
        self.drops: Dict[str, int] = collections.Counter()
        self.received: Dict[str, int] = collections.Counter()
        self.windows_emitted = 0
        self.reconfigure(config)

    def reconfigure(self, config: WindowConfig) -> None:
        """Take new settings for the next frames (same cameras); buffered frames stay. A
        ``descriptor_dim`` of 0 is taken from the next frame again."""
        if tuple(config.cameras) != tuple(self._buffers):
            raise ValueError(f"reconfigure: cameras {list(config.cameras)} differ from {list(self._buffers)}")
        self.config = config
        self.descriptor_dim = config.descriptor_dim
        self._tolerance_ns = duration_ns(config.sync_tolerance)
        self._settle_ns = self._tolerance_ns + duration_ns(config.max_delay)
        self._max_age_ns = duration_ns(config.max_age)
        self._max_future_ns = duration_ns(config.max_future)

    def _drop(self, reason: str, count: int = 1) -> None:
        self.drops[reason] += count

    def add(self, frame: Frame, now_ns: Optional[int] = None) -> List[List[Frame]]:
        """Buffer one frame; returns the windows it completes (usually zero or one).

        ``now_ns``: the caller's clock (frames far ahead of it are dropped), None = no check.
        Invalid frames are dropped and counted (``drops``); this never raises for bad input.
        """
        cfg = self.config
        if self.descriptor_dim == 0 and frame.count > 0 and np.ndim(frame.descriptors) == 2:
            self.descriptor_dim = int(np.shape(frame.descriptors)[1])
        if frame.camera_id not in self._buffers:
            self._drop("unknown_camera")
            return []
        self.received[frame.camera_id] += 1
        if not isinstance(frame.stamp_ns, (int, np.integer)):
            self._drop("bad_stamp")
            return []
        stamp = int(frame.stamp_ns)
        if now_ns is not None and stamp > now_ns + self._max_future_ns:
            self._drop("future")
            return []
        last = self._last_stamp.get(frame.camera_id)
        if last is not None and stamp <= last:
            self._drop("out_of_order")
            return []
        try:
            frame = validate_frame(frame, cfg, self.descriptor_dim)
        except FrameError as exc:
            self._drop(exc.reason)
            return []
        self._last_stamp[frame.camera_id] = stamp
        buf = self._buffers[frame.camera_id]
        buf.append(frame)
        if len(buf) > cfg.buffer_size:
            buf.popleft()
            self._drop("overflow")
        self._newest = stamp if self._newest is None else max(self._newest, stamp)
        self._expire()
        windows = []
        while True:
            window = self._try_window()
            if window is None:
                break
            windows.append(window)
        return windows

    def _expire(self) -> None:
        for buf in self._buffers.values():
            while buf and buf[0].stamp_ns < self._newest - self._max_age_ns:
                buf.popleft()
                self._drop("stale")

    def _try_window(self, settled_all: bool = False) -> Optional[List[Frame]]:
        cfg = self.config
        heads = [b[0].stamp_ns for b in self._buffers.values() if b]
        if not heads:
            return None
        anchor = min(heads)
        chosen: Dict[str, Frame] = {}
        for cam, buf in self._buffers.items():
            near = [f for f in buf if abs(f.stamp_ns - anchor) <= self._tolerance_ns]
            if near:
                chosen[cam] = min(near, key=lambda f: abs(f.stamp_ns - anchor))
        complete = len(chosen) == len(cfg.cameras)
        settled = settled_all or self._newest > anchor + self._settle_ns
        if not (complete or settled):
            return None
        # Consume the chosen frames and everything older in their buffers; the anchor frame always goes.
        for cam, buf in self._buffers.items():
            if cam in chosen:
                while buf and buf[0].stamp_ns <= chosen[cam].stamp_ns:
                    buf.popleft()
        if len(chosen) < cfg.min_views:
            self._drop("incomplete", len(chosen))
            return None if not any(self._buffers.values()) else self._try_window(settled_all)
        self.windows_emitted += 1
        return [chosen[c] for c in cfg.cameras if c in chosen]

    def flush(self) -> List[List[Frame]]:
        """Emit what can still form windows at end of input (bag end), dropping the rest."""
        windows = []
        while True:
            w = self._try_window(settled_all=True)  # no frame can come any more
            if w is None:
                break
            windows.append(w)
        leftover = sum(len(b) for b in self._buffers.values())
        if leftover:
            self._drop("incomplete", leftover)
            for b in self._buffers.values():
                b.clear()
        return windows
