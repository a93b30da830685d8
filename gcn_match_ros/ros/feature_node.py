"""feature_node: camera images -> keypoints and descriptors (OpenCV SIFT or ORB).

Subscribes ``image`` (sensor_msgs/Image; mono8, bgr8, rgb8) and, optionally,
``camera_info`` (sensor_msgs/CameraInfo, the latest one is attached to every output), both
with sensor-data QoS; publishes ``keypoints`` (gcn_match_msgs/Keypoints, reliable, so both
best-effort and reliable subscribers match). All names are relative: run one node per
camera in the camera's namespace, e.g.::

    python -m gcn_match_ros.ros.feature_node --ros-args -r __ns:=/cam0 -p camera_id:=cam0

Detection is :func:`gcn_match_ros.detect.extract_features` — the same as the offline
data sets the model is trained on (one keypoint per location, strongest response first;
ORB descriptors travel as packed bits). The callback handles the newest image only: the
subscription keeps one image (sensor-data QoS, depth 1), so a slow detector skips frames
instead of queueing them. Bad images (unknown encoding, wrong sizes) are counted by reason,
logged (throttled) and skipped.
"""
from __future__ import annotations

import collections
import sys
import threading
import time
from typing import Optional

import cv2
import numpy as np
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor, ParameterType, SetParametersResult
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image

from gcn_match_msgs.msg import Keypoints

from ..detect import DETECTOR_KINDS, extract_features
from ..stamps import stamp_to_ns
from ..windowing import Frame
from .conversions import frame_to_keypoints
from .spin import run_node

__all__ = ["FeatureNode", "ImageError", "image_to_gray", "DETECTORS", "main"]

DETECTORS = ("sift", "orb")
_CHANNELS = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3}
_THROTTLE_S = 5.0


class ImageError(ValueError):
    """An image that cannot be used; ``reason`` is a short counter key."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def image_to_gray(msg: Image) -> np.ndarray:
    """An 8-bit mono/BGR/RGB Image as a (H, W) uint8 grayscale array.

    Raises:
        ImageError: unsupported encoding (``encoding``), zero size (``empty``), a row stride
            shorter than a row (``bad_step``) or too little data (``bad_size``).
    """
    enc = msg.encoding.lower()
    if enc not in _CHANNELS:
        raise ImageError("encoding", f"unsupported encoding '{msg.encoding}' (use mono8, bgr8 or rgb8)")
    c = _CHANNELS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise ImageError("empty", f"image is {w}x{h}")
    if step < w * c:
        raise ImageError("bad_step", f"step {step} is shorter than a row of {w}x{c} bytes")
    data = np.frombuffer(msg.data, np.uint8)
    if data.size < step * h:
        raise ImageError("bad_size", f"{data.size} bytes of data for {h} rows of step {step} "
                                     f"(expected {step * h})")
    img = data[:step * h].reshape(h, step)[:, :w * c]
    if c == 1:
        return np.ascontiguousarray(img)
    img = img.reshape(h, w, 3)
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY if enc == "rgb8" else cv2.COLOR_BGR2GRAY)


class FeatureNode(Node):
    """See the module docstring; ``**kwargs`` go to :class:`rclpy.node.Node`."""

    def __init__(self, node_name: str = "feature_node", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        try:
            self._setup()
        except Exception:
            self.destroy_node()
            raise

    def _setup(self) -> None:
        self.declare_parameter("detector", "sift", ParameterDescriptor(
            description="Keypoint detector and descriptor: sift (128 floats) or orb (256 bits).",
            type=ParameterType.PARAMETER_STRING, additional_constraints="sift | orb"))
        self.declare_parameter("max_features", 1000, ParameterDescriptor(
            description="Keypoints requested from the detector (before de-duplication).",
            integer_range=[IntegerRange(from_value=1, to_value=100000, step=1)]))
        self.declare_parameter("camera_id", "cam0", ParameterDescriptor(
            description="Camera id written into every Keypoints message.", read_only=True,
            type=ParameterType.PARAMETER_STRING))
        detector = self.get_parameter("detector").value
        if detector not in DETECTORS:
            raise ValueError(f"parameter detector='{detector}': must be one of {', '.join(DETECTORS)}")
        self._detector = detector
        self._max_features = int(self.get_parameter("max_features").value)
        self._camera_id = self.get_parameter("camera_id").value
        if not self._camera_id:
            raise ValueError("parameter camera_id must not be empty")
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self._lock = threading.Lock()
        self._camera_info: Optional[CameraInfo] = None
        self.images_received = 0
        self.keypoints_published = 0
        self.bad_images: collections.Counter = collections.Counter()
        self._pub = self.create_publisher(Keypoints, "keypoints", QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE))
        image_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                               reliability=qos_profile_sensor_data.reliability,
                               durability=qos_profile_sensor_data.durability)
        self.create_subscription(Image, "image", self._on_image, image_qos)
        self.create_subscription(CameraInfo, "camera_info", self._on_camera_info, qos_profile_sensor_data)
        self.get_logger().info(f"{self._detector} (max_features {self._max_features}) for camera "
                               f"'{self._camera_id}': {self.resolve_topic_name('image')} -> "
                               f"{self._pub.topic_name}")

    def _on_set_parameters(self, params) -> SetParametersResult:
        for p in params:
            if p.name == "detector" and p.value not in DETECTORS:
                return SetParametersResult(successful=False,
                                           reason=f"detector must be one of {', '.join(DETECTORS)}")
        with self._lock:
            for p in params:
                if p.name == "detector":
                    self._detector = p.value
                elif p.name == "max_features":
                    self._max_features = int(p.value)
        return SetParametersResult(successful=True)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        with self._lock:
            self._camera_info = msg

    def _bad(self, reason: str, text: str) -> None:
        with self._lock:
            self.bad_images[reason] += 1
            counts = dict(self.bad_images)
        self.get_logger().warning(f"skipped an image: {text} (bad images so far: {counts})",
                                  throttle_duration_sec=_THROTTLE_S)

    def _on_image(self, msg: Image) -> None:
        with self._lock:
            self.images_received += 1
            detector, max_features, info = self._detector, self._max_features, self._camera_info
        try:
            gray = image_to_gray(msg)
        except ImageError as exc:
            self._bad(exc.reason, str(exc))
            return
        t = time.perf_counter()
        try:
            feats = extract_features(gray, detector=detector, max_features=max_features)
        except cv2.error as exc:
            self._bad("detector_error", f"OpenCV: {exc}")
            return
        h, w = gray.shape
        if info is not None and (info.width, info.height) not in ((w, h), (0, 0)):
            self.get_logger().warning(f"camera_info is {info.width}x{info.height} but the image is {w}x{h}: "
                                      "not attached", throttle_duration_sec=_THROTTLE_S)
            info = None
        frame = Frame(camera_id=self._camera_id, stamp_ns=stamp_to_ns(msg.header.stamp),
                      keypoints=feats.keypoints, descriptors=feats.descriptors, frame_id=msg.header.frame_id,
                      scales=feats.scales, orientations=feats.orientations, image_size=(w, h),
                      binary=DETECTOR_KINDS[detector][1], descriptor_name=detector)
        out = frame_to_keypoints(frame, camera_info=info)  # without camera_info: the image size, uncalibrated
        self._pub.publish(out)
        with self._lock:
            self.keypoints_published += 1
        self.get_logger().debug(f"{out.count} {detector} keypoints in {1e3 * (time.perf_counter() - t):.1f} ms")


def main(args=None) -> int:
    """Console script ``feature_node``; returns the exit status (1: invalid parameters)."""
    return run_node(FeatureNode, "feature_node", args)


if __name__ == "__main__":
    sys.exit(main())
