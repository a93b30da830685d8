"""gcn_match_ros: multi-camera keypoint matching with a graph neural network (ROS 2 Jazzy)."""

__version__ = "0.1.0"
