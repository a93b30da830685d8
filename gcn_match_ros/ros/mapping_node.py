"""mapping_node: an example mapping consumer — persistent landmarks into a 3-D map.

Subscribes the matcher's ``matches`` (``MatchWindow`` with ``landmark_ids``), every camera's
``<camera>/keypoints`` (pixel coordinates and ``camera_info`` intrinsics) and, where poses are
available, ``<camera>/pose`` (``geometry_msgs/PoseStamped``: the camera's optical frame in the
world, as the sample bags carry it). With poses, each window's sightings go into a
:class:`gcn_match_ros.landmark_map.LandmarkMap` (landmarks seen from two or more poses are
triangulated and kept when they reproject within 3 px in front of every camera) and the map is
published as ``~/landmarks`` (``sensor_msgs/PointCloud2``: x, y, z float32, ``id`` and
``sightings`` uint32, in the poses' frame). Before a window enters the map, the map predicts
it: the reprojection error of every sighting of an already mapped landmark in that held-out
window (``held_out_px``: the last ``held_out_window`` of them; logged as median and share
within 3 px) — what a consumer sees of wrong id continuations. Without poses it still reports
landmark statistics (landmarks in the window, continued from the previous one, new; throttled
log); a window with a pose that is none (a NaN position, an all-zero quaternion) is not mapped
and counted (``windows with an invalid pose``).

Callbacks only buffer (the last ``buffer`` keypoint and pose messages per camera); windows are
processed in the MatchWindow callback, a bounded amount of work per window.
"""
from __future__ import annotations

import collections
import sys

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import PointCloud2, PointField

from gcn_match_msgs.msg import Keypoints, MatchWindow

from ..geometry import pose_msg_to_rt
from ..landmark_map import LandmarkMap
from .frame_buffer import StampBuffer, decoded_window, window_frames
from .spin import run_node

__all__ = ["MappingNode", "landmark_cloud", "main"]

NODE_NAME = "mapping_node"
_THROTTLE_S = 2.0


def landmark_cloud(ids: np.ndarray, points: np.ndarray, sightings: np.ndarray, header) -> PointCloud2:
    """A PointCloud2 of landmarks: x, y, z (float32), id, sightings (uint32); 20 bytes a point."""
    dtype = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4"), ("sightings", "<u4")])
    data = np.zeros(len(ids), dtype)
    if len(ids):
        data["x"], data["y"], data["z"] = points[:, 0], points[:, 1], points[:, 2]
        data["id"], data["sightings"] = ids.astype(np.uint32), sightings.astype(np.uint32)
    fields = [PointField(name=n, offset=dtype.fields[n][1], datatype=PointField.FLOAT32 if n in "xyz" else
                         PointField.UINT32, count=1) for n in dtype.names]
    return PointCloud2(header=header, height=1, width=len(ids), fields=fields, is_bigendian=False,
                       point_step=dtype.itemsize, row_step=dtype.itemsize * len(ids), data=data.tobytes(),
                       is_dense=True)


class MappingNode(Node):
    """See the module docstring. ``**kwargs`` go to :class:`rclpy.node.Node`."""

    def __init__(self, node_name: str = NODE_NAME, **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.declare_parameter("cameras", ["cam0", "cam1", "cam2"])
        self.declare_parameter("buffer", 30)
        cameras = [str(c) for c in self.get_parameter("cameras").value]
        depth = int(self.get_parameter("buffer").value)
        self._keypoints, self._poses = StampBuffer(cameras, depth), StampBuffer(cameras, depth)
        self.map = LandmarkMap()
        self.counts = collections.Counter()
        self._previous = set()
        self._all = set()
        #: held-out reprojection errors [px] of the latest sightings of mapped landmarks
        self.held_out_px = collections.deque(maxlen=2000)
        for cam in cameras:
            self.create_subscription(Keypoints, f"{cam}/keypoints", lambda m, c=cam: self._keypoints.add(c, m),
                                     qos_profile_sensor_data)
            self.create_subscription(PoseStamped, f"{cam}/pose", lambda m, c=cam: self._poses.add(c, m),
                                     QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE))
        self.create_subscription(MatchWindow, "matches", self._on_window, 10)
        self._pub = self.create_publisher(PointCloud2, "~/landmarks", 2)
        self.get_logger().info(f"mapping landmarks of {cameras} -> {self._pub.topic_name}")

    def _on_window(self, msg: MatchWindow) -> None:
        w = decoded_window(msg, self.counts, self.get_logger(), _THROTTLE_S)
        if w is None:
            return
        if w.landmark_ids is None:
            self.counts["windows without landmarks"] += 1
            self.get_logger().warning("the matcher publishes no landmark ids", throttle_duration_sec=_THROTTLE_S)
            return
        current = set(w.landmark_ids[w.landmark_ids >= 0].tolist())
        stats = (f"{len(current)} landmarks in the window, {len(current & self._previous)} continued, "
                 f"{len(current - self._all)} new")
        self._previous, self._all = current, self._all | current
        frames, why = window_frames(w, self._keypoints)
        poses = [self._poses.find(f.camera_id, f.stamp_ns) for f in frames] if frames else []
        if frames is None or any(p is None for p in poses) or any(f.K is None for f in frames):
            self.counts["windows without poses"] += 1
            self.get_logger().info(f"{stats}; not mapped ({why or 'no pose or intrinsics for every view'})",
                                   throttle_duration_sec=_THROTTLE_S)
            return
        try:
            Rt = [pose_msg_to_rt(p.pose) for p in poses]
        except ValueError as exc:  # a NaN position, an all-zero quaternion: no sighting from it
            self.counts["windows with an invalid pose"] += 1
            self.get_logger().warning(f"{stats}; not mapped: {exc}", throttle_duration_sec=_THROTTLE_S)
            return
        window = (w.landmark_ids, np.concatenate([f.keypoints for f in frames]), w.view_index,
                  np.stack([f.K for f in frames]), np.stack([r for r, _ in Rt]), np.stack([t for _, t in Rt]))
        self.held_out_px.extend(self.map.held_out_errors(*window).tolist())  # before the map has seen it
        self.map.add_window(*window, w.stamp_ns)
        ids, points, sightings = self.map.arrays()
        header = msg.header
        header.frame_id = poses[0].header.frame_id
        self._pub.publish(landmark_cloud(ids, points, sightings, header))
        self.counts["maps published"] += 1
        held_out = np.asarray(self.held_out_px)
        if held_out.size:
            stats += (f"; held-out reprojection median {np.median(held_out):.1f} px, "
                      f"{np.mean(held_out <= self.map.config.max_reprojection_px):.0%} within "
                      f"{self.map.config.max_reprojection_px:g} px (last {held_out.size} sightings)")
        self.get_logger().info(f"{stats}; {len(ids)} landmarks mapped", throttle_duration_sec=_THROTTLE_S)


def main(args=None) -> int:
    """Console script ``mapping_node``."""
    return run_node(MappingNode, NODE_NAME, args)


if __name__ == "__main__":
    sys.exit(main())
