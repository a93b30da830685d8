"""Cameras -> one feature_node per camera -> matcher_node: wiring only, no logic.

    ros2 launch gcn_match_ros gcn_match.launch.py cameras:=front,left,right \
        params_file:=$(ros2 pkg prefix gcn_match_ros)/share/gcn_match_ros/config/rig4.yaml

Each camera ``c`` gets a feature_node in namespace ``<namespace>/<c>`` that reads
``<namespace>/<c>/<image_topic>`` (and ``camera_info`` beside it) and publishes
``<namespace>/<c>/keypoints``; the matcher_node in ``<namespace>`` subscribes those and
publishes ``<namespace>/matcher_node/matches``. The parameter file sets the matcher (every
parameter: config/matcher.yaml); ``cameras`` given here overrides the file's. ROS launch is not
on PyPI: test/test_launch.py checks this file's names against the package without running it.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = "gcn_match_ros"
FEATURE_EXECUTABLE = "feature_node"
MATCHER_EXECUTABLE = "matcher_node"
DEFAULT_PARAMS_FILE = "config/matcher.yaml"  # in the package's share directory
FEATURE_PARAMETERS = ("camera_id", "detector")
MATCHER_PARAMETERS = ("cameras",)
ARGUMENTS = {
    "cameras": ("cam0,cam1,cam2", "comma-separated camera ids, in window order"),
    "namespace": ("", "namespace of the whole pipeline"),
    "params_file": ("", "matcher parameter file (default: the package's config/matcher.yaml)"),
    "detector": ("sift", "feature_node detector: sift or orb"),
    "image_topic": ("image_raw", "each camera's image topic, relative to its namespace"),
}


def _nodes(context):
    arg = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    cameras = [c.strip() for c in arg["cameras"].split(",") if c.strip()]
    params_file = arg["params_file"] or [FindPackageShare(PACKAGE), "/" + DEFAULT_PARAMS_FILE]
    ns = arg["namespace"].rstrip("/")
    nodes = [Node(package=PACKAGE, executable=FEATURE_EXECUTABLE, name=f"{cam}_features",
                  namespace=f"{ns}/{cam}", remappings=[("image", arg["image_topic"])],
                  parameters=[dict(zip(FEATURE_PARAMETERS, (cam, arg["detector"])))])
             for cam in cameras]
    nodes.append(Node(package=PACKAGE, executable=MATCHER_EXECUTABLE, name=MATCHER_EXECUTABLE, namespace=ns or "/",
                      parameters=[params_file, dict(zip(MATCHER_PARAMETERS, (cameras,)))]))
    return nodes


def generate_launch_description():
    return LaunchDescription([DeclareLaunchArgument(name, default_value=default, description=doc)
                              for name, (default, doc) in ARGUMENTS.items()] + [OpaqueFunction(function=_nodes)])
