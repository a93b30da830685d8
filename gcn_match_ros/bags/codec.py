"""The ``gcn_match_msgs/Keypoints`` codec: one encoder and one decoder between a
:class:`~gcn_match_ros.windowing.Frame` and the message, for rosbags messages (bags) and
rclpy messages (``ros/conversions.py``) alike.

The encoder (:func:`keypoints_fields`) gives the field values, which each side puts into
its own message class; the decoder (:func:`frame_from_keypoints_msg`) reads attributes
only, so it takes either kind of message and this core module never imports rclpy. Binary descriptors (ORB, ...) travel packed (``np.packbits``,
MSB first) and are unpacked to 0/1 float32 columns in the Frame, as
:func:`gcn_match_ros.detect.extract_features` gives them to the trainer. A malformed
message raises :class:`~gcn_match_ros.windowing.FrameError` whose ``reason`` is a short
counter key (``count_mismatch``, ``bad_shape``, ``descriptor_type``, ``descriptor_dim``,
``too_large``, ``bad_intrinsics``, ``camera_mismatch``).
"""
from __future__ import annotations

import array
from typing import Any, Dict, Optional

import numpy as np

from ..geometry import rt_to_pose
from ..stamps import ns_to_sec_nanosec, stamp_to_ns
from ..windowing import Frame, FrameError
from .typesys import CAMERA_INFO_TYPE, HEADER_TYPE, KEYPOINTS_TYPE, typestore

__all__ = ["HARD_MAX_KEYPOINTS", "DESCRIPTOR_FLOAT", "DESCRIPTOR_BINARY", "BINARY_DESCRIPTORS", "WORLD_FRAME",
           "keypoints_fields", "camera_info_fields", "keypoints_msg", "message_array", "frame_from_keypoints_msg",
           "header_msg", "camera_info_msg", "pose_msg"]

#: Descriptor names that are binary, for frames made from problems (which keep no descriptor type).
BINARY_DESCRIPTORS = ("orb", "brief", "brisk", "akaze", "freak")
DESCRIPTOR_FLOAT, DESCRIPTOR_BINARY = 0, 1
#: Keypoints messages announcing more keypoints than this are rejected (``too_large``)
#: before any array is touched; the node's ``max_keypoints`` then trims what is accepted.
HARD_MAX_KEYPOINTS = 1_000_000
WORLD_FRAME = "world"


def header_msg(T, stamp_ns: int, frame_id: str):
    """A rosbags ``std_msgs/Header`` (``T``: the type store's types)."""
    sec, nsec = ns_to_sec_nanosec(stamp_ns)
    return T[HEADER_TYPE](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame_id)


def camera_info_fields(K: Optional[np.ndarray], image_size) -> Dict[str, Any]:
    """The ``sensor_msgs/CameraInfo`` fields (but ``header`` and ``roi``) of an undistorted camera:
    K (all zero when None: uncalibrated) and the image size (0 x 0 when None)."""
    w, h = (int(image_size[0]), int(image_size[1])) if image_size is not None else (0, 0)
    if K is None:
        k, p, d, model = np.zeros(9), np.zeros(12), np.zeros(0), ""
    else:
        K = np.asarray(K, dtype=np.float64)
        k, p = K.ravel(), np.c_[K, np.zeros(3)].ravel()
        d, model = np.zeros(5), "plumb_bob"  # undistorted images
    return dict(height=h, width=w, distortion_model=model, d=d, k=k, r=np.eye(3).ravel(), p=p, binning_x=0,
                binning_y=0)


def camera_info_msg(T, header, K: Optional[np.ndarray], image_size) -> object:
    """A rosbags ``sensor_msgs/CameraInfo`` (:func:`camera_info_fields`)."""
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return T[CAMERA_INFO_TYPE](header=header, roi=roi, **camera_info_fields(K, image_size))


def _f32(a) -> np.ndarray:
    return np.zeros(0, np.float32) if a is None else np.ascontiguousarray(a, dtype=np.float32).ravel()


def keypoints_fields(frame: Frame) -> Dict[str, Any]:
    """The encoder: every ``Keypoints`` field of ``frame`` but ``header`` and ``camera_info``
    (numpy arrays of the fields' element types, and scalars).

    A binary frame (:attr:`Frame.binary`) must hold 0/1 descriptors; they travel packed
    (``np.packbits``, MSB first) in ``descriptors_binary``, ``descriptor_dim`` counting bits.

    Raises:
        ValueError: a binary frame whose descriptors are not all 0 or 1.
    """
    desc = np.asarray(frame.descriptors)
    n, dim = int(desc.shape[0]), int(desc.shape[1]) if desc.ndim == 2 else 0
    if frame.binary:
        if np.any((desc != 0) & (desc != 1)):
            raise ValueError(f"{frame.descriptor_name or 'binary'} descriptors must be unpacked bits (0/1)")
        packed = np.packbits(desc.astype(np.uint8), axis=1).ravel() if n else np.zeros(0, np.uint8)
    return dict(camera_id=frame.camera_id, count=n, keypoints=_f32(frame.keypoints), scales=_f32(frame.scales),
                orientations=_f32(frame.orientations), scores=_f32(frame.scores),
                descriptor_type=DESCRIPTOR_BINARY if frame.binary else DESCRIPTOR_FLOAT,
                descriptor_name=frame.descriptor_name.lower(), descriptor_dim=dim,
                descriptors=np.zeros(0, np.float32) if frame.binary else _f32(desc),
                descriptors_binary=packed if frame.binary else np.zeros(0, np.uint8))


def keypoints_msg(frame: Frame, store=None):
    """A rosbags ``gcn_match_msgs/msg/Keypoints`` for ``frame`` (:func:`keypoints_fields`; stamp,
    frame_id, K and image_size into the header and camera_info)."""
    T = (store or typestore()).types
    header = header_msg(T, frame.stamp_ns, frame.frame_id)
    return T[KEYPOINTS_TYPE](header=header, camera_info=camera_info_msg(T, header, frame.K, frame.image_size),
                             **keypoints_fields(frame))


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
    return Frame(camera_id=cam, stamp_ns=stamp_to_ns(msg.header.stamp), keypoints=kp.reshape(n, 2),
                 descriptors=desc, frame_id=msg.header.frame_id, scales=optional(msg.scales, "scales"),
                 orientations=optional(msg.orientations, "orientations"),
                 scores=optional(msg.scores, "scores"), K=K,
                 image_size=(w, h) if w > 0 and h > 0 else None,
                 binary=msg.descriptor_type == DESCRIPTOR_BINARY, descriptor_name=str(msg.descriptor_name))


def pose_msg(T, stamp_ns: int, R: np.ndarray, t: np.ndarray):
    """A rosbags ``geometry_msgs/PoseStamped`` of a camera in ``world`` from its world->camera
    (R, t) (:func:`gcn_match_ros.geometry.rt_to_pose`)."""
    pos, q = rt_to_pose(R, t)
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=pos[0], y=pos[1], z=pos[2]),
        orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    return T["geometry_msgs/msg/PoseStamped"](header=header_msg(T, stamp_ns, WORLD_FRAME), pose=pose)
