"""Keypoint frames in rosbag2 bags, without ROS (pure-Python ``rosbags``; never rclpy).

Import what you need from the modules (the bag tools need only :mod:`.io` and :mod:`.typesys`,
and so load neither torch nor the rest of the package):

- :mod:`.typesys`: the type store with ``gcn_match_msgs``; :mod:`.codec`: the one
  ``Keypoints`` encoder and decoder; :mod:`.io`: reading and writing bag files;
- :mod:`.contents`: the topic layout, a bag's frames, labels and windows;
- :mod:`.source`: a bag's windows as training problems; :mod:`.make`: sample bags.
"""
