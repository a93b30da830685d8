"""ROS side of gcn_match_ros: nodes, message conversions, bag tools and the demo.

Modules here import rclpy and the generated ``gcn_match_msgs`` messages; the core package
(``gcn_match_ros``) does not, so it stays usable without ROS. This ``__init__`` itself
imports nothing from ROS.

- nodes: :mod:`.matcher_node` (its parameters :mod:`.parameters`, its counters
  :mod:`.diagnostics`), :mod:`.feature_node`, :mod:`.example_consumer`;
- :mod:`.conversions` (messages <-> core types), :mod:`.spin` (the life cycle of an executable
  node), :mod:`.dds` (Fast DDS settings for large messages);
- :mod:`.bag_play`, :mod:`.bag_record`, :mod:`.demo`; :mod:`.testing`, the harness the tests,
  the demo and the benchmarks share.
"""
