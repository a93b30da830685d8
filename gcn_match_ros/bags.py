"""rosbag2 bags of keypoint frames (mcap or sqlite3), without ROS: write, read, window.

Core module: uses ``rosbags`` and numpy only (never rclpy), so the trainer, the
evaluator and the tests read bags exactly as recorded, and ``ros/bag_play.py`` /
``ros/bag_record.py`` reuse it for the file side.

Topic layout (per camera ``<cam>``, e.g. ``cam0``; all stamps are image stamps)
-------------------------------------------------------------------------------
- ``/<cam>/keypoints`` (``gcn_match_msgs/msg/Keypoints``): keypoints + descriptors of one
  image, ``camera_info`` embedded; ``header.frame_id = "<cam>_optical_frame"``.
- ``/<cam>/camera_info`` (``sensor_msgs/msg/CameraInfo``): the same calibration, same
  stamp (all-zero ``k``: uncalibrated).
- ``/<cam>/pose`` (``geometry_msgs/msg/PoseStamped``): pose of ``<cam>_optical_frame`` in
  ``world`` (only frames with R, t, e.g. scenes with poses).
- ``/<cam>/gt_labels`` (``gcn_match_msgs/msg/KeypointLabels``): scene-global ground truth
  per keypoint (bags made from datasets).

The messages of one frame share ``header.stamp`` and the bag's log time equals that
stamp, so the bag's order is stamp order (what a live rig publishes).

Pose convention
---------------
``/<cam>/pose`` is the camera's optical frame (z forward, x right, y down) expressed in
``world``: ``header.frame_id = "world"``, ``position`` = camera centre ``C`` and
``orientation`` = the rotation ``R_wc`` taking camera coordinates to world
coordinates (camera->world, the usual tf convention). The problem format
(``shared/spec/problem-format.md``) uses world->camera ``R, t`` with
``x ~ K (R X + t)``; the two are related by::

    R = R_wc^T,   t = -R_wc^T C        (pose -> problem: :func:`pose_to_rt`)
    R_wc = R^T,   C = -R^T t           (problem -> pose: :func:`rt_to_pose`)

Labels
------
``KeypointLabels.labels[i]`` labels keypoint ``i`` of the Keypoints message with the
same camera and stamp: ``>= 0`` id of the imaged scene point, ``-1`` no partner in any
other image of the scene, ``-2`` unlabelled. A dataset scene is labelled *once over all
its images* (``datasets.label_homography`` / ``datasets.label_poses``), so ids are
consistent across every frame of the bag and any window can be scored. Within one window
an id that occurs once has no partner there: :func:`window_labels` maps it to ``-1``
(equivalent for pair scoring, and what ``gt_track`` means in a problem file).

Scene -> bag design (:func:`convert_scene_to_bag`)
---------------------------------------------------
A dataset scene is V images of one static scene taken from V viewpoints (Oxford: a
planar scene, exact homographies; Strecha/Middlebury: calibrated poses). The bag shows
it as a **rig of C cameras sliding along the image sequence**: at time step k,
camera ``cam<j>`` (j = 0..C-1) sees image k + j, for k = 0..V-C. Each time step is one
synchronised rig capture and therefore exactly one matching window of C views (with
the default :class:`WindowConfig`), e.g. Oxford graf, C = 3: windows (img1, img2, img3),
(img2, img3, img4), ..., (img4, img5, img6) — the same consecutive windows as
``datasets.sample_windows``. Every frame is a real image (no image is shown twice by
one camera, nothing is re-published with invented jitter); an image appears in up to
C steps, seen by different cameras, with identical keypoints and labels each time.

Stamps: step k at ``start_time + k / rate_hz``; camera j is stamped ``j * stagger``
later (default 2 ms: a software-triggered rig), well inside the default 50 ms
``sync_tolerance``. Keypoints come from ``datasets.extract_features`` (SIFT by
default, or ORB: packed into ``descriptors_binary``), at most ``max_features`` per
image, strongest first (``scores`` empty). ``camera_info`` holds the scene's K (pose
scenes) or an all-zero K (Oxford: uncalibrated) and the image size; pose scenes also
get ``/<cam>/pose``.
"""
from __future__ import annotations

import array
import dataclasses
import functools
import math
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Dict, Iterator, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import numpy as np

from .windowing import Frame, FrameError, WindowAssembler, WindowConfig, validate_frame

__all__ = [
    "BagError", "BagContents", "BagInfo", "typestore", "ensure_type", "find_msg_file",
    "write_scene_bag", "read_bag", "bag_windows", "bag_info", "iter_raw", "window_labels",
    "convert_scene_to_bag", "frame_from_keypoints_msg", "message_array", "HARD_MAX_KEYPOINTS", "keypoints_msg", "rt_to_pose",
    "pose_to_rt", "quat_to_matrix", "matrix_to_quat", "restamp_cdr", "has_header",
    "stamp_to_ns", "ns_to_stamp", "KEYPOINTS_TYPE", "LABELS_TYPE", "CAMERA_INFO_TYPE",
    "POSE_TYPE", "BINARY_DESCRIPTORS",
]

MSG_PACKAGE = "gcn_match_msgs"
OUR_TYPES = ("Keypoints", "MatchWindow", "KeypointLabels")
KEYPOINTS_TYPE = "gcn_match_msgs/msg/Keypoints"
LABELS_TYPE = "gcn_match_msgs/msg/KeypointLabels"
MATCH_WINDOW_TYPE = "gcn_match_msgs/msg/MatchWindow"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
HEADER_TYPE = "std_msgs/msg/Header"
WORLD_FRAME = "world"
BINARY_DESCRIPTORS = ("orb", "brief", "brisk", "akaze", "freak")
DESCRIPTOR_FLOAT, DESCRIPTOR_BINARY = 0, 1

#: Keypoints messages announcing more keypoints than this are rejected (``too_large``)
#: before any array is touched; the node's ``max_keypoints`` then trims what is accepted.
HARD_MAX_KEYPOINTS = 1_000_000
STORAGES = ("mcap", "sqlite3")
_SRC_MSG_DIR = Path(__file__).resolve().parents[1] / "msg_defs" / "msg"


class BagError(ValueError):
    """A bag that cannot be read or written (missing, truncated, corrupt, wrong types);
    the message names the file."""


# --------------------------------------------------------------------------------------
# Type store
# --------------------------------------------------------------------------------------
def _share_msg_dirs(package: str) -> List[Path]:
    """``<prefix>/share/<package>/msg`` for every prefix on AMENT_PREFIX_PATH, then the
    interpreter's prefix (the venv the message package was installed into)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [sys.prefix]
    dirs: List[Path] = []
    for p in prefixes:
        d = Path(p) / "share" / package / "msg"
        if d.is_dir() and d not in dirs:
            dirs.append(d)
    return dirs


def find_msg_file(msgtype: str) -> Path:
    """The ``.msg`` file of ``pkg/msg/Name``: an installed share dir first (what the
    generated rclpy classes were built from), then, for gcn_match_msgs, the source tree's
    ``msg_defs/msg``.

    Raises:
        BagError: no such file anywhere.
    """
    pkg, _, name = _split_type(msgtype)
    dirs = _share_msg_dirs(pkg)
    if pkg == MSG_PACKAGE:
        dirs.append(_SRC_MSG_DIR)
    for d in dirs:
        f = d / f"{name}.msg"
        if f.is_file():
            return f
    raise BagError(f"no definition of {msgtype}: {name}.msg not found in "
                   f"{[str(d) for d in dirs] or 'any share/' + pkg + '/msg (is AMENT_PREFIX_PATH set?)'}")


def _split_type(msgtype: str) -> Tuple[str, str, str]:
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise BagError(f"not a message type name (pkg/msg/Name): {msgtype!r}")
    return parts[0], parts[1], parts[2]


def ensure_type(store, msgtype: str) -> str:
    """Register ``msgtype`` (and the types it uses) in ``store`` from installed ``.msg``
    files if it is not known yet; returns the normalised name ``pkg/msg/Name``."""
    from rosbags.typesys import get_types_from_msg

    pkg, kind, name = _split_type(msgtype)
    full = f"{pkg}/{kind}/{name}"
    if full in store.fielddefs:
        return full
    types = get_types_from_msg(find_msg_file(full).read_text(), full)
    store.register(types)
    for _, (_, fields) in types.items():
        for _, (nodetype, spec) in fields:
            for ref in _referenced(nodetype, spec):
                ensure_type(store, ref)
    return full


def _referenced(nodetype, spec) -> List[str]:
    """Message type names a field definition refers to."""
    from rosbags.typesys.msg import Nodetype  # type: ignore[attr-defined]

    if nodetype == Nodetype.NAME:
        return [spec]
    if nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        (sub_type, sub_spec), _ = spec
        return _referenced(sub_type, sub_spec)
    return []


@functools.lru_cache(maxsize=None)
def typestore():
    """The rosbags type store for ROS 2 Jazzy with gcn_match_msgs registered (shared,
    cached: do not register conflicting definitions in it)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in OUR_TYPES:
        full = f"{MSG_PACKAGE}/msg/{name}"
        types.update(get_types_from_msg(find_msg_file(full).read_text(), full))
    store.register(types)
    return store


# --------------------------------------------------------------------------------------
# Stamps, poses
# --------------------------------------------------------------------------------------
def stamp_to_ns(stamp: float) -> int:
    """Seconds (float) -> integer nanoseconds, such that ``ns_to_stamp(stamp_to_ns(s)) == s``.

    A float holds epoch seconds only to ~0.24 us, so several ns values map to one float;
    this picks the roundest of them (``1700000000.102`` -> ``1700000000102000000`` ns, not
    ``...101999998``), so stamps made from round numbers stay round in the bag.
    """
    f = float(stamp)
    if not math.isfinite(f):
        raise ValueError(f"stamp must be finite, got {stamp!r}")
    sec = math.floor(f)
    base = sec * 10**9 + int(round((f - sec) * 1e9))  # f - sec is exact
    for q in (10**9, 10**8, 10**7, 10**6, 10**5, 10**4, 10**3, 10**2, 10):
        cand = (base + q // 2) // q * q
        if ns_to_stamp(cand) == f:
            return cand
    return base


def ns_to_stamp(ns: int) -> float:
    """Integer nanoseconds -> float seconds, the way every Frame.stamp is computed
    (``sec + nanosec * 1e-9`` of the header)."""
    sec, nsec = divmod(int(ns), 10**9)
    return sec + nsec * 1e-9


def _time_stamp(msg_stamp) -> float:
    return int(msg_stamp.sec) + int(msg_stamp.nanosec) * 1e-9


def _time_ns(msg_stamp) -> int:
    return int(msg_stamp.sec) * 10**9 + int(msg_stamp.nanosec)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quat_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Quaternion (x, y, z, w) (normalised here) -> rotation matrix (3, 3)."""
    x, y, z, w = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rt_to_pose(R: np.ndarray, t: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """World->camera (R, t) of the problem format -> camera pose in world for PoseStamped:
    (position C = -R^T t (3,), orientation of R_wc = R^T as quaternion x, y, z, w (4,))."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(3)
    return -R.T @ t, matrix_to_quat(R.T)


def pose_to_rt(position: Sequence[float], quat_xyzw: Sequence[float]) -> Tuple[np.ndarray, np.ndarray]:
    """PoseStamped (camera->world: position C, orientation R_wc) -> world->camera
    ``R = R_wc^T``, ``t = -R C``."""
    R = quat_to_matrix(quat_xyzw).T
    return R, -R @ np.asarray(position, dtype=np.float64).reshape(3)


# --------------------------------------------------------------------------------------
# Message <-> Frame
# --------------------------------------------------------------------------------------
def _header(T, stamp_ns: int, frame_id: str):
    sec, nsec = divmod(int(stamp_ns), 10**9)
    return T[HEADER_TYPE](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def _camera_info(T, header, K: Optional[np.ndarray], image_size) -> object:
    w, h = (int(image_size[0]), int(image_size[1])) if image_size is not None else (0, 0)
    if K is None:
        k, p, d, model = np.zeros(9), np.zeros(12), np.zeros(0), ""
    else:
        K = np.asarray(K, dtype=np.float64)
        k, p = K.ravel(), np.c_[K, np.zeros(3)].ravel()
        d, model = np.zeros(5), "plumb_bob"  # undistorted images
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T[CAMERA_INFO_TYPE](header=header, height=h, width=w, distortion_model=model, d=d, k=k,
                               r=np.eye(3).ravel(), p=p, binning_x=0, binning_y=0, roi=roi)


def _f32(a) -> np.ndarray:
    return np.zeros(0, np.float32) if a is None else np.ascontiguousarray(a, dtype=np.float32).ravel()


def keypoints_msg(frame: Frame, descriptor_name: str = "sift", store=None):
    """A rosbags ``gcn_match_msgs/msg/Keypoints`` for ``frame`` (stamp, frame_id, K and
    image_size into the header and camera_info). Binary descriptor names
    (:data:`BINARY_DESCRIPTORS`) expect 0/1 descriptors and pack them (np.packbits)."""
    T = (store or typestore()).types
    header = _header(T, stamp_to_ns(frame.stamp), frame.frame_id)
    desc = np.asarray(frame.descriptors)
    n, dim = int(desc.shape[0]), int(desc.shape[1]) if desc.ndim == 2 else 0
    binary = descriptor_name.lower() in BINARY_DESCRIPTORS
    if binary:
        if np.any((desc != 0) & (desc != 1)):
            raise ValueError(f"{descriptor_name} descriptors must be unpacked bits (0/1)")
        packed = np.packbits(desc.astype(np.uint8), axis=1).ravel() if n else np.zeros(0, np.uint8)
    return T[KEYPOINTS_TYPE](
        header=header, camera_id=frame.camera_id,
        camera_info=_camera_info(T, header, frame.K, frame.image_size), count=n,
        keypoints=_f32(frame.keypoints), scales=_f32(frame.scales), orientations=_f32(frame.orientations),
        scores=_f32(frame.scores), descriptor_type=DESCRIPTOR_BINARY if binary else DESCRIPTOR_FLOAT,
        descriptor_name=descriptor_name.lower(), descriptor_dim=dim,
        descriptors=np.zeros(0, np.float32) if binary else _f32(desc),
        descriptors_binary=packed if binary else np.zeros(0, np.uint8))


def message_array(field, dtype) -> np.ndarray:
    """Read-only numpy view of a message array field (array.array, bytes, numpy array or list)."""
    if isinstance(field, (array.array, bytes, bytearray, memoryview)):
        return np.frombuffer(field, dtype)
    return np.asarray(field, dtype)


def frame_from_keypoints_msg(msg, camera_id: Optional[str] = None,
                             max_count: int = HARD_MAX_KEYPOINTS) -> Frame:
    """A ``Keypoints`` message as a :class:`Frame` (arrays are views of the message).

    Works on rclpy messages and on rosbags-decoded ones alike (same fields); only
    attributes are read, so this core module never imports rclpy.

    Args:
        msg: the message.
        camera_id: the camera the message arrived for (its topic); an empty
            ``msg.camera_id`` takes it, a different one is rejected (``camera_mismatch``).
        max_count: messages announcing more keypoints are rejected (``too_large``).

    Shapes of the result: keypoints (N, 2) float32, descriptors (N, D) float32 (binary
    descriptors unpacked to 0/1), scales/orientations/scores (N,) or None, K (3, 3) or None
    (all-zero ``camera_info.k`` = uncalibrated), image_size (width, height) or None.

    Raises:
        FrameError: malformed message, with a counter ``reason``. Content checks (empty,
            NaN/inf, descriptor dimension of the window, ``max_keypoints``) are left to
            :func:`gcn_match_ros.windowing.validate_frame`, which the assembler runs.
    """
    cam = msg.camera_id
    if camera_id is not None:
        if cam and cam != camera_id:
            raise FrameError("camera_mismatch",
                             f"camera_id '{cam}' arrived on the topic of camera '{camera_id}'")
        cam = camera_id
    if not cam:
        raise FrameError("camera_mismatch", "message has an empty camera_id")
    n = int(msg.count)
    if n > max_count:
        raise FrameError("too_large", f"count {n} exceeds the limit of {max_count} keypoints")
    stamp = _time_stamp(msg.header.stamp)
    kp = message_array(msg.keypoints, np.float32)
    if kp.size != 2 * n:
        raise FrameError("count_mismatch", f"keypoints: {kp.size} values for count {n} (expected {2 * n})")
    dim = int(msg.descriptor_dim)
    if msg.descriptor_type == DESCRIPTOR_FLOAT:
        if len(msg.descriptors_binary):
            raise FrameError("bad_shape", "descriptors_binary must be empty for float descriptors")
        raw = message_array(msg.descriptors, np.float32)
        if n and dim == 0:
            raise FrameError("descriptor_dim", "descriptor_dim is 0 but the frame has keypoints")
        if raw.size != n * dim:
            raise FrameError("count_mismatch",
                             f"descriptors: {raw.size} values for count {n} x dim {dim} (expected {n * dim})")
        desc = raw.reshape(n, dim)
    elif msg.descriptor_type == DESCRIPTOR_BINARY:
        if len(msg.descriptors):
            raise FrameError("bad_shape", "descriptors must be empty for binary descriptors")
        raw = message_array(msg.descriptors_binary, np.uint8)
        if n and dim == 0:
            raise FrameError("descriptor_dim", "descriptor_dim is 0 but the frame has keypoints")
        nbytes = (dim + 7) // 8
        if raw.size != n * nbytes:
            raise FrameError("count_mismatch", f"descriptors_binary: {raw.size} bytes for count {n} x "
                                               f"{nbytes} bytes (dim {dim} bits, expected {n * nbytes})")
        desc = np.unpackbits(raw.reshape(n, nbytes), axis=1)[:, :dim].astype(np.float32)
    else:
        raise FrameError("descriptor_type", f"unknown descriptor_type {msg.descriptor_type} "
                                            f"(expected {DESCRIPTOR_FLOAT} or {DESCRIPTOR_BINARY})")

    def optional(field, name):
        a = message_array(field, np.float32)
        if a.size == 0:
            return None
        if a.size != n:
            raise FrameError("bad_shape", f"{name}: {a.size} values for count {n} (expected {n} or 0)")
        return a

    k = np.asarray(msg.camera_info.k, np.float64).reshape(3, 3)
    if not np.all(np.isfinite(k)):
        raise FrameError("bad_intrinsics", "camera_info.k contains NaN or inf")
    K = k if np.any(k != 0.0) else None
    w, h = int(msg.camera_info.width), int(msg.camera_info.height)
    return Frame(camera_id=cam, stamp=stamp, keypoints=kp.reshape(n, 2), descriptors=desc,
                 frame_id=msg.header.frame_id, scales=optional(msg.scales, "scales"),
                 orientations=optional(msg.orientations, "orientations"),
                 scores=optional(msg.scores, "scores"), K=K,
                 image_size=(w, h) if w > 0 and h > 0 else None)


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------
def _open_writer(path: Path, storage: str, compress: bool):
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

    if storage not in STORAGES:
        raise ValueError(f"storage must be one of {STORAGES}, got {storage!r}")
    writer = Writer(path, version=Writer.VERSION_LATEST,
                    storage_plugin=StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3)
    if compress and storage == "mcap":
        # zstd chunk compression inside the mcap file (what rosbag2's own mcap plugin
        # writes); readable with or without metadata.yaml.
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    return writer


class _BagWriter:
    """Writes a rosbag2 bag; ``path`` ending in ``.mcap`` gives a single mcap file,
    anything else a rosbag2 directory (metadata.yaml + storage file)."""

    def __init__(self, path, storage: str = "mcap", compress: bool = True) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"{self.path}: exists already, not overwriting")
        self.single = self.path.suffix == ".mcap"
        if self.single and storage != "mcap":
            raise ValueError(f"{self.path}: a .mcap path needs storage='mcap'")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        self._bag_dir = self._tmp / self.path.stem
        self.writer = _open_writer(self._bag_dir, storage, compress)
        self.store = typestore()
        self.connections: Dict[str, object] = {}
        self.writer.open()

    def connection(self, topic: str, msgtype: str):
        conn = self.connections.get(topic)
        if conn is None:
            ensure_type(self.store, msgtype)
            conn = self.writer.add_connection(topic, msgtype, typestore=self.store)
            self.connections[topic] = conn
        elif conn.msgtype != msgtype:
            raise BagError(f"{self.path}: topic {topic} has type {conn.msgtype}, not {msgtype}")
        return conn

    def write_raw(self, topic: str, msgtype: str, log_ns: int, raw: bytes) -> None:
        self.writer.write(self.connection(topic, msgtype), int(log_ns), raw)

    def write(self, topic: str, msgtype: str, log_ns: int, msg) -> None:
        self.write_raw(topic, msgtype, log_ns, bytes(self.store.serialize_cdr(msg, msgtype)))

    def close(self) -> Path:
        """Finalise (index, metadata) and move the result into place atomically."""
        self.writer.close()
        try:
            if self.single:
                os.replace(self._bag_dir / f"{self.path.stem}.mcap", self.path)
            else:
                os.replace(self._bag_dir, self.path)
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        try:
            self.writer.abort()
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "_BagWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_scene_bag(path, frames_by_camera: Mapping[str, Sequence[Frame]],
                    labels: Optional[Mapping[str, Sequence[Optional[np.ndarray]]]] = None, *,
                    storage: str = "mcap", descriptor_name: str = "sift", label_method: str = "",
                    sources: Optional[Mapping[str, Sequence[str]]] = None,
                    compress: bool = True, progress: bool = False) -> Path:
    """Write frames (and optional labels) as a bag in the layout of the module docstring.

    Everything per frame comes from the :class:`Frame`: ``stamp`` (header stamp and log
    time), ``frame_id`` (default ``<cam>_optical_frame``), ``K`` and ``image_size``
    (``camera_info``, embedded and on ``/<cam>/camera_info``), ``R, t`` (world->camera;
    written as the camera->world ``/<cam>/pose``, only for frames that have them).

    Args:
        path: ``*.mcap`` -> a single mcap file; else a rosbag2 directory of ``storage``.
        frames_by_camera: camera id -> frames in stamp order (topic namespace = camera id).
        labels: camera id -> per-frame (N,) int labels (scene-global ids, -1, -2) or None,
            parallel to ``frames_by_camera``; published on ``/<cam>/gt_labels``.
        descriptor_name: e.g. "sift" (float) or "orb" (0/1 bits, packed in the message).
        label_method, sources: ``KeypointLabels.method`` and per-frame ``.source`` strings.

    Returns:
        ``path``. The bag appears there only once complete (written aside, then renamed).
    """
    from tqdm import tqdm

    items = []
    for order, (cam, frames) in enumerate(frames_by_camera.items()):
        cam_labels = (labels or {}).get(cam)
        cam_sources = (sources or {}).get(cam)
        for i, f in enumerate(frames):
            if f.camera_id != cam:
                raise ValueError(f"frame {i} of camera {cam!r} has camera_id {f.camera_id!r}")
            lab = cam_labels[i] if cam_labels is not None else None
            if lab is not None and len(lab) != f.count:
                raise ValueError(f"labels of {cam} frame {i}: {len(lab)} values for {f.count} keypoints")
            items.append((stamp_to_ns(f.stamp), order, f, lab, cam_sources[i] if cam_sources else ""))
    items.sort(key=lambda x: (x[0], x[1]))
    with _BagWriter(path, storage, compress) as bag:
        T = bag.store.types
        for ns, _, f, lab, src in tqdm(items, desc=f"writing {Path(path).name}", unit="frame",
                                       disable=not progress):
            cam = f.camera_id
            if not f.frame_id:
                f = dataclasses.replace(f, frame_id=f"{cam}_optical_frame")
            header = _header(T, ns, f.frame_id)
            bag.write(f"/{cam}/camera_info", CAMERA_INFO_TYPE, ns, _camera_info(T, header, f.K, f.image_size))
            if f.R is not None and f.t is not None:
                pos, q = rt_to_pose(f.R, f.t)
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=pos[0], y=pos[1], z=pos[2]),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
                bag.write(f"/{cam}/pose", POSE_TYPE, ns,
                          T[POSE_TYPE](header=_header(T, ns, WORLD_FRAME), pose=pose))
            if lab is not None:
                bag.write(f"/{cam}/gt_labels", LABELS_TYPE, ns, T[LABELS_TYPE](
                    header=header, camera_id=cam, labels=np.asarray(lab, dtype=np.int64),
                    method=label_method, source=src))
            bag.write(f"/{cam}/keypoints", KEYPOINTS_TYPE, ns, keypoints_msg(f, descriptor_name, bag.store))
    return Path(path)


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------
class BagInfo(NamedTuple):
    """Summary of a bag: topic -> type, topic -> message count, first and last log time (ns)."""

    path: Path
    topics: Dict[str, str]
    counts: Dict[str, int]
    start_ns: int
    end_ns: int
    message_count: int


def _wrap(path, exc: BaseException) -> BagError:
    text = str(exc).strip() or type(exc).__name__
    if isinstance(exc, FileNotFoundError):
        return BagError(f"{path}: no such bag ({text})")
    return BagError(f"{path}: unreadable bag, truncated or corrupt? ({type(exc).__name__}: {text})")


class _Reader:
    """rosbags Reader with every failure turned into BagError naming the file, and types
    rebuilt from the definitions stored in the bag (falling back to ours)."""

    def __init__(self, path) -> None:
        from rosbags.rosbag2 import Reader

        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag")
        try:
            self.reader = Reader(self.path)
            self.reader.open()
        except Exception as exc:  # ReaderError, struct errors, yaml, ...
            raise _wrap(self.path, exc) from None
        self.store = self._store()

    def _store(self):
        """Standard Jazzy types, then the definitions stored in the bag (a bag written with an
        older Keypoints.msg decodes with its own definition), then ours for the rest."""
        from rosbags.interfaces import MessageDefinitionFormat
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        store = get_typestore(Stores.ROS2_JAZZY)
        for conn in self.reader.connections:
            if conn.msgdef.format == MessageDefinitionFormat.MSG and conn.msgdef.data:
                try:
                    types = get_types_from_msg(conn.msgdef.data, conn.msgtype)
                except Exception:  # noqa: BLE001 - fall back to the installed definition
                    continue
                store.register({k: v for k, v in types.items() if k not in store.fielddefs})
        try:
            ours = typestore().fielddefs
        except BagError:  # our .msg files are not installed here: the bag's own definitions serve
            ours = {}
        store.register({k: v for k, v in ours.items() if k not in store.fielddefs})
        return store

    def info(self) -> BagInfo:
        r = self.reader
        topics = {c.topic: c.msgtype for c in r.connections}
        counts: Dict[str, int] = {}
        for c in r.connections:
            counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
        count = r.message_count
        return BagInfo(self.path, topics, counts, r.start_time if count else 0,
                       r.end_time - 1 if count else 0, count)

    def messages(self, topics: Optional[Sequence[str]] = None) -> Iterator[Tuple[str, str, int, bytes]]:
        conns = [c for c in self.reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        try:
            for conn, ns, raw in self.reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, ns, raw
        except BagError:
            raise
        except Exception as exc:
            raise _wrap(self.path, exc) from None

    def decode(self, raw: bytes, msgtype: str):
        try:
            return self.store.deserialize_cdr(raw, msgtype)
        except Exception as exc:
            raise BagError(f"{self.path}: cannot decode a {msgtype} message "
                           f"({type(exc).__name__}: {exc})") from None

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception:  # noqa: BLE001
            pass

    def __enter__(self) -> "_Reader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def bag_info(path) -> BagInfo:
    """Topics, types and counts of a bag (mcap/db3 file or rosbag2 directory).

    Raises:
        BagError: missing, truncated or corrupt bag.
    """
    with _Reader(path) as r:
        return r.info()


def iter_raw(path, topics: Optional[Sequence[str]] = None) -> Iterator[Tuple[str, str, int, bytes]]:
    """``(topic, msgtype, log_time_ns, cdr_bytes)`` in log-time order (what a player
    publishes). Raises :class:`BagError` (at open or mid-way) for truncated/corrupt bags."""
    with _Reader(path) as r:
        yield from r.messages(topics)


def has_header(msgtype: str, store=None) -> bool:
    """True when the type's first field is a ``std_msgs/msg/Header`` (restampable)."""
    store = store or typestore()
    try:
        ensure_type(store, msgtype)
    except BagError:
        return False
    fields = store.fielddefs[_normalise(msgtype)][1]
    return bool(fields) and fields[0][1][1] == HEADER_TYPE


def _normalise(msgtype: str) -> str:
    pkg, kind, name = _split_type(msgtype)
    return f"{pkg}/{kind}/{name}"


def restamp_cdr(raw: bytes, offset_ns: int) -> bytes:
    """Shift the header stamp of a CDR message whose first field is a std_msgs/Header
    by ``offset_ns`` (the stamp is the first 8 bytes after the 4-byte encapsulation).

    Raises:
        ValueError: too short, or a stamp that would become negative.
    """
    if len(raw) < 12:
        raise ValueError("CDR message too short to hold a header stamp")
    endian = "<" if raw[1] & 1 else ">"
    sec = int(np.frombuffer(raw, dtype=endian + "i4", count=1, offset=4)[0])
    nsec = int(np.frombuffer(raw, dtype=endian + "u4", count=1, offset=8)[0])
    total = sec * 10**9 + nsec + int(offset_ns)
    if total < 0:
        raise ValueError("restamped header stamp would be negative")
    sec, nsec = divmod(total, 10**9)
    out = bytearray(raw)
    out[4:8] = np.array([sec], dtype=endian + "i4").tobytes()
    out[8:12] = np.array([nsec], dtype=endian + "u4").tobytes()
    return bytes(out)


@dataclasses.dataclass
class BagContents:
    """Frames of a bag.

    Attributes:
        path: the bag.
        topics: topic -> message type; counts: topic -> messages.
        frames: camera id -> frames (Keypoints messages) in bag order, with K, image_size and,
            when the bag has ``<ns>/pose`` at the same stamp, R, t (world->camera).
        labels: camera id -> per-frame (N,) int64 labels or None, parallel to ``frames``.
        sources: camera id -> per-frame ``KeypointLabels.source`` ("" if none).
        order: (camera id, index) of every frame in bag (log-time) order: the order a
            player publishes them, and the order :meth:`windows` feeds the assembler.
        descriptor_names: camera id -> ``Keypoints.descriptor_name`` of its first frame.
    """

    path: Path
    topics: Dict[str, str]
    counts: Dict[str, int]
    frames: Dict[str, List[Frame]]
    labels: Dict[str, List[Optional[np.ndarray]]]
    sources: Dict[str, List[str]]
    order: List[Tuple[str, int]]
    descriptor_names: Dict[str, str]

    @property
    def cameras(self) -> List[str]:
        """Camera ids, natural order (cam2 before cam10)."""
        return sorted(self.frames, key=lambda c: [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", c)])

    @property
    def n_frames(self) -> int:
        return len(self.order)

    def frames_in_order(self) -> Iterator[Frame]:
        for cam, i in self.order:
            yield self.frames[cam][i]

    def labels_of(self, frame: Frame) -> Optional[np.ndarray]:
        """Labels of a frame of this bag (looked up by camera id and stamp)."""
        return self._index().get((frame.camera_id, frame.stamp), (None, None))[1]

    def _index(self) -> Dict[Tuple[str, float], Tuple[Frame, Optional[np.ndarray]]]:
        idx = getattr(self, "_idx", None)
        if idx is None:
            idx = {(f.camera_id, f.stamp): (f, self.labels[c][i])
                   for c, fs in self.frames.items() for i, f in enumerate(fs)}
            object.__setattr__(self, "_idx", idx)
        return idx

    def windows(self, config: WindowConfig, flush: bool = True
                ) -> Iterator[Tuple[List[Frame], Optional[np.ndarray]]]:
        """Feed the frames to a :class:`WindowAssembler` in bag order, as the matcher node
        does on replay (``add(frame)``; stamps in the past never hit ``max_future``; a
        ``descriptor_dim`` of 0 is fixed by the first frame, as the node does), and
        yield each window's frames (validated copies, views in ``config.cameras`` order)
        with their labels concatenated in the same rows as ``window_problem(frames)``
        ((N,) int64 scene-global labels, or None when a frame has none). ``flush``: also
        emit what is left at the end of the bag."""
        assembler = WindowAssembler(config)
        for frame in self.frames_in_order():
            if assembler.config.descriptor_dim == 0 and frame.count > 0 and np.ndim(frame.descriptors) == 2:
                # like the node: descriptor_dim 0 = take it from the first frame
                assembler.config = dataclasses.replace(assembler.config,
                                                       descriptor_dim=int(frame.descriptors.shape[1]))
            for window in assembler.add(frame):
                yield window, self._window_labels(window, config)
        if flush:
            for window in assembler.flush():
                yield window, self._window_labels(window, config)

    def _window_labels(self, window: Sequence[Frame], config: WindowConfig) -> Optional[np.ndarray]:
        parts = []
        idx = self._index()
        for f in window:
            orig, lab = idx.get((f.camera_id, f.stamp), (None, None))
            if lab is None or orig is None:
                return None
            if orig.count != f.count:  # the assembler kept max_keypoints of them: same rows
                lab = lab[_kept_rows(orig, config)]
            parts.append(np.asarray(lab, dtype=np.int64))
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _kept_rows(frame: Frame, config: WindowConfig) -> np.ndarray:
    """Rows of ``frame`` that validate_frame keeps (it trims to max_keypoints): run it on a
    copy whose descriptors are the row numbers."""
    rows = np.arange(frame.count, dtype=np.float64)[:, None]
    probe = dataclasses.replace(frame, descriptors=rows, orientations=None, scales=None, K=None)
    cfg = dataclasses.replace(config, descriptor_dim=0)
    return validate_frame(probe, cfg).descriptors[:, 0].astype(np.int64)


def window_labels(labels: np.ndarray) -> np.ndarray:
    """Scene-global labels of one window -> the window's ``gt_track``: ids >= 0 that occur
    only once in the window become -1 (their partners are outside the window)."""
    labels = np.asarray(labels, dtype=np.int64)
    out = labels.copy()
    pos = labels >= 0
    if pos.any():
        ids, counts = np.unique(labels[pos], return_counts=True)
        single = np.isin(labels, ids[counts == 1]) & pos
        out[single] = -1
    return out


def read_bag(path, progress: Optional[bool] = None) -> BagContents:
    """Read every Keypoints frame of a bag with its pose and labels.

    Frames come from topics of type Keypoints (camera id = ``Keypoints.camera_id``, else the
    topic's namespace). A ``PoseStamped`` topic in the same namespace (``/<cam>/pose``)
    with the same stamp gives the frame's R, t (converted to world->camera); a
    ``KeypointLabels`` message with the same camera id and stamp gives its labels.

    Args:
        progress: tqdm bar; None = only for bags of more than 500 messages.

    Raises:
        BagError: missing, truncated or corrupt bag, or labels that do not fit their frame.
    """
    from tqdm import tqdm

    with _Reader(path) as r:
        info = r.info()
        show = info.message_count > 500 if progress is None else progress
        frames: Dict[str, List[Frame]] = {}
        order: List[Tuple[str, int]] = []
        ns_of: Dict[Tuple[str, int], str] = {}  # (camera, stamp ns) -> topic namespace
        frame_ns: Dict[Tuple[str, int], Tuple[str, int]] = {}
        poses: Dict[Tuple[str, int], Tuple[np.ndarray, np.ndarray]] = {}
        labels: Dict[Tuple[str, int], Tuple[np.ndarray, str]] = {}
        names: Dict[str, str] = {}
        wanted = {t for t, ty in info.topics.items() if ty in (KEYPOINTS_TYPE, LABELS_TYPE, POSE_TYPE)}
        bar = tqdm(total=info.message_count, desc=f"reading {Path(path).name}", unit="msg", disable=not show)
        with bar:
            for topic, msgtype, _, raw in r.messages(sorted(wanted)):
                bar.update(1)
                ns = topic.rsplit("/", 1)[0]
                if msgtype == KEYPOINTS_TYPE:
                    msg = r.decode(raw, msgtype)
                    try:
                        frame = frame_from_keypoints_msg(msg, camera_id=str(msg.camera_id) or ns.strip("/") or topic)
                    except ValueError as exc:  # counts that do not fit the arrays
                        raise BagError(f"{path}: malformed Keypoints message on {topic} at "
                                       f"{_time_stamp(msg.header.stamp):.9f}: {exc}") from None
                    cam = frame.camera_id or ns.strip("/") or topic
                    if frame.camera_id != cam:
                        frame = dataclasses.replace(frame, camera_id=cam)
                    stamp_ns = _time_ns(msg.header.stamp)
                    lst = frames.setdefault(cam, [])
                    names.setdefault(cam, str(msg.descriptor_name))
                    frame_ns[(cam, stamp_ns)] = (cam, len(lst))
                    order.append((cam, len(lst)))
                    ns_of[(cam, stamp_ns)] = ns
                    lst.append(frame)
                elif msgtype == POSE_TYPE:
                    msg = r.decode(raw, msgtype)
                    p, q = msg.pose.position, msg.pose.orientation
                    poses[(ns, _time_ns(msg.header.stamp))] = pose_to_rt([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
                else:
                    msg = r.decode(raw, msgtype)
                    labels[(str(msg.camera_id), _time_ns(msg.header.stamp))] = (
                        np.asarray(msg.labels, dtype=np.int64).copy(), str(msg.source))
            bar.update(info.message_count - bar.n)
    out_labels = {c: [None] * len(fs) for c, fs in frames.items()}
    out_sources = {c: [""] * len(fs) for c, fs in frames.items()}
    for key, (cam, i) in frame_ns.items():
        pose = poses.get((ns_of[key], key[1]))
        if pose is not None:
            frames[cam][i] = dataclasses.replace(frames[cam][i], R=pose[0], t=pose[1])
        lab = labels.get(key)
        if lab is not None:
            if len(lab[0]) != frames[cam][i].count:
                raise BagError(f"{path}: labels of {cam} at {ns_to_stamp(key[1]):.9f} have {len(lab[0])} "
                               f"values for {frames[cam][i].count} keypoints")
            out_labels[cam][i], out_sources[cam][i] = lab
    return BagContents(path=Path(path), topics=info.topics, counts=info.counts, frames=frames,
                       labels=out_labels, sources=out_sources, order=order, descriptor_names=names)


def bag_windows(path, window_config: WindowConfig, progress: Optional[bool] = None
                ) -> Iterator[Tuple[List[Frame], Optional[np.ndarray]]]:
    """The windows of a bag, formed by :class:`WindowAssembler` exactly as the matcher node
    forms them on replay: ``(frames, labels)`` per window (see :meth:`BagContents.windows`;
    ``windowing.window_problem(frames)`` stacks them, ``labels`` has the same rows)."""
    yield from read_bag(path, progress=progress).windows(window_config)


# --------------------------------------------------------------------------------------
# Dataset scene -> bag
# --------------------------------------------------------------------------------------
def convert_scene_to_bag(data_root, scene: str, out_path, *, n_cameras: int = 3, detector: str = "sift",
                         max_features: int = 500, rate_hz: float = 2.0, stagger: float = 0.002,
                         start_time: float = 1_700_000_000.0, storage: str = "mcap",
                         progress: bool = True) -> Path:
    """Write a dataset scene as a bag of a C-camera rig sliding along its images (design in
    the module docstring): step k, camera ``cam<j>`` sees image k + j.

    Args:
        data_root: ``shared/data``; scene: e.g. ``oxford/graf``, ``strecha/fountain-P11``.
        n_cameras: C, 2 <= C <= number of images (pose scenes: the labeller needs >= 3 images).
        detector, max_features: ``datasets.extract_features`` settings.
        rate_hz: rig captures per second; stagger: camera j is stamped j * stagger later.
        start_time: stamp of the first capture, seconds (fixed: bags are reproducible).

    Raises:
        datasets.DatasetError: missing or malformed scene; ValueError: bad settings.
    """
    import cv2
    from tqdm import tqdm

    from . import datasets

    sc = datasets.load_scene(Path(data_root), scene)
    V = sc.n_views
    if not 2 <= n_cameras <= V:
        raise ValueError(f"n_cameras must be in [2, {V}] for {scene}, got {n_cameras}")
    if rate_hz <= 0 or stagger < 0 or stagger * (n_cameras - 1) >= 1.0 / rate_hz:
        raise ValueError("need rate_hz > 0 and 0 <= stagger * (n_cameras - 1) < 1 / rate_hz")
    feats = []
    for p in tqdm(sc.image_paths, desc=f"{detector} {scene}", unit="image", disable=not progress):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise datasets.DatasetError(f"{p}: not a readable image")
        feats.append(datasets.extract_features(img, detector, max_features))
    kps = [f.keypoints for f in feats]
    if sc.kind == "homography":
        gt = datasets.label_homography(kps, sc.homographies, sc.image_sizes)
        method = f"homography:{sc.name}"
    else:
        gt = datasets.label_poses(kps, sc.K, sc.R, sc.t)
        method = f"poses:{sc.name}"
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])])
    per_image = [gt[offsets[v]:offsets[v + 1]] for v in range(V)]
    root = Path(data_root)
    rel = [str(p.relative_to(root)) if p.is_relative_to(root) else p.name for p in sc.image_paths]
    cams = [f"cam{j}" for j in range(n_cameras)]
    start_ns, stagger_ns = stamp_to_ns(start_time), int(round(stagger * 1e9))
    frames: Dict[str, List[Frame]] = {c: [] for c in cams}
    labels: Dict[str, List[np.ndarray]] = {c: [] for c in cams}
    sources: Dict[str, List[str]] = {c: [] for c in cams}
    for k in range(V - n_cameras + 1):
        for j, cam in enumerate(cams):
            v = k + j
            f = feats[v]
            frames[cam].append(Frame(
                camera_id=cam, stamp=ns_to_stamp(start_ns + int(round(k * 1e9 / rate_hz)) + j * stagger_ns),
                keypoints=f.keypoints, descriptors=f.descriptors, frame_id=f"{cam}_optical_frame",
                scales=f.scales, orientations=f.orientations, scores=None,
                K=None if sc.K is None else sc.K[v], image_size=tuple(int(x) for x in sc.image_sizes[v]),
                R=None if sc.R is None else sc.R[v], t=None if sc.t is None else sc.t[v]))
            labels[cam].append(per_image[v])
            sources[cam].append(rel[v])
    return write_scene_bag(out_path, frames, labels, storage=storage, descriptor_name=detector,
                           label_method=method, sources=sources, progress=progress)
