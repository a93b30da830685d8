"""visualizer_node: what the matcher does, as an image a user opens in an image viewer.

Subscribes, for every camera in ``cameras``, ``<camera>/keypoints`` (the matcher's input, for
the keypoint coordinates) and ``<camera>/<image>`` (``sensor_msgs/Image``, or with
``compressed:=true`` ``<camera>/<image>/compressed``, ``sensor_msgs/CompressedImage``), and the
matcher's ``matches`` (``MatchWindow``); publishes ``~/image`` (``sensor_msgs/Image``, bgr8):
the window's views side by side with every track in one colour
(:func:`gcn_match_ros.track_image.draw_tracks`).

Bounded cost: callbacks only buffer (the last ``buffer`` keypoint frames and images per camera,
the newest window only); a timer draws the newest window at most ``max_rate`` times a second,
so when drawing cannot keep up, windows are skipped (counted) rather than queued. A window's
views are found by their exact stamps (MatchWindow.view_stamps = the Keypoints headers, which
feature_node copies from the image headers); a view whose keypoints are gone is counted and the
window skipped, one whose image is missing is drawn blank.
"""
from __future__ import annotations

import collections
import sys
from typing import Optional

import cv2
import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image

from gcn_match_msgs.msg import Keypoints, MatchWindow

from ..track_image import draw_tracks
from .frame_buffer import StampBuffer, decoded_window, window_frames
from .spin import run_node

__all__ = ["VisualizerNode", "main", "image_to_bgr"]

NODE_NAME = "visualizer_node"
_THROTTLE_S = 5.0


def image_to_bgr(msg) -> np.ndarray:
    """A ``sensor_msgs/Image`` (mono8, bgr8, rgb8) or ``CompressedImage`` as a BGR / grey array.

    Raises:
        ValueError: an unknown encoding, a size that does not fit the data, undecodable bytes.
    """
    if isinstance(msg, CompressedImage):
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"cannot decode a compressed image ({msg.format or 'unknown format'})")
        return img
    channels = {"mono8": 1, "bgr8": 3, "rgb8": 3}.get(msg.encoding)
    if channels is None:
        raise ValueError(f"image encoding '{msg.encoding}' (mono8, bgr8 or rgb8 only)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if step < w * channels or data.size < h * step:
        raise ValueError(f"image {w} x {h} ({msg.encoding}) does not fit {data.size} bytes of step {step}")
    img = data[:h * step].reshape(h, step)[:, :w * channels].reshape(h, w, channels)
    if channels == 1:
        return img[:, :, 0]
    return img[:, :, ::-1] if msg.encoding == "rgb8" else img


class VisualizerNode(Node):
    """See the module docstring. ``**kwargs`` go to :class:`rclpy.node.Node`."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("cameras", ["cam0", "cam1", "cam2"])
        self.declare_parameter("image", "image")
        self.declare_parameter("compressed", False)
        self.declare_parameter("height", 360)
        self.declare_parameter("max_rate", 5.0)
        self.declare_parameter("buffer", 30)
        cameras = [str(c) for c in self.get_parameter("cameras").value]
        depth = max(int(self.get_parameter("buffer").value), 1)
        self._height = max(int(self.get_parameter("height").value), 16)
        self._keypoints, self._images = StampBuffer(cameras, depth), StampBuffer(cameras, depth)
        self._window: Optional[MatchWindow] = None
        self.counts = collections.Counter()
        image_type = CompressedImage if self.get_parameter("compressed").value else Image
        suffix = self.get_parameter("image").value + ("/compressed" if image_type is CompressedImage else "")
        for cam in cameras:
            self.create_subscription(Keypoints, f"{cam}/keypoints", lambda m, c=cam: self._keypoints.add(c, m),
                                     qos_profile_sensor_data)
            self.create_subscription(image_type, f"{cam}/{suffix}", lambda m, c=cam: self._images.add(c, m),
                                     qos_profile_sensor_data)
        self.create_subscription(MatchWindow, "matches", self._on_window, 10)
        self._pub = self.create_publisher(Image, "~/image", 2)
        self.create_timer(1.0 / max(float(self.get_parameter("max_rate").value), 0.1), self._draw_newest)
        self.get_logger().info(f"drawing windows of {cameras} on {self._pub.topic_name}")

    # -- callbacks: buffer only -----------------------------------------------------------
    def _on_window(self, msg: MatchWindow) -> None:
        if self._window is not None:
            self.counts["windows skipped"] += 1  # the previous one was never drawn: drawing is behind
        self._window = msg

    # -- drawing (timer) --------------------------------------------------------------------
    def _draw_newest(self) -> None:
        msg, self._window = self._window, None
        if msg is None:
            return
        w = decoded_window(msg, self.counts, self.get_logger(), _THROTTLE_S)
        if w is None:
            return
        frames, why = window_frames(w, self._keypoints)
        if frames is None:
            self.counts["windows without keypoints"] += 1
            self.get_logger().warning(f"skipped a window: {why}", throttle_duration_sec=_THROTTLE_S)
            return
        images = []
        for f in frames:
            image_msg = self._images.find(f.camera_id, f.stamp_ns)
            img = None
            if image_msg is not None:
                try:
                    img = image_to_bgr(image_msg)
                except ValueError as exc:
                    self.counts["bad images"] += 1
                    self.get_logger().warning(f"{f.camera_id}: {exc}", throttle_duration_sec=_THROTTLE_S)
            else:
                self.counts["views without image"] += 1
            images.append(img)
        keypoints, sizes = [f.keypoints for f in frames], [f.image_size for f in frames]
        canvas = draw_tracks(images, keypoints, w.track, image_sizes=sizes, height=self._height,
                             title=f"{w.method}: {w.track_count} tracks over {len(images)} views")
        out = Image(header=msg.header, height=canvas.shape[0], width=canvas.shape[1], encoding="bgr8",
                    is_bigendian=0, step=canvas.shape[1] * 3, data=canvas.tobytes())
        self._pub.publish(out)
        self.counts["images published"] += 1


def main(args=None) -> int:
    """Console script ``visualizer_node``."""
    return run_node(VisualizerNode, NODE_NAME, args)


if __name__ == "__main__":
    sys.exit(main())
