"""Keypoint frames in rosbag2 bags, without ROS (pure-Python ``rosbags``; never rclpy).

- :mod:`.typesys`: the type store with ``gcn_match_msgs``; :mod:`.codec`: the one
  ``Keypoints`` encoder and decoder; :mod:`.io`: reading and writing bag files;
- :mod:`.contents`: the topic layout, a bag's frames, labels and windows;
- :mod:`.source`: a bag's windows as training problems; :mod:`.make`: sample bags.
"""
from .contents import BagContents, read_bag, write_scene_bag
from .io import BagError, bag_info
from .source import BagSource

__all__ = ["BagContents", "BagError", "BagSource", "bag_info", "read_bag", "write_scene_bag"]
