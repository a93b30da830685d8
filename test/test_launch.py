"""Tests of launch/gcn_match.launch.py without ROS launch (not installable from PyPI): the file
parses, and every executable, parameter and file it names exists in the package."""
import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "gcn_match.launch.py"


def _constants() -> dict:
    tree = ast.parse(LAUNCH.read_text())
    out = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            try:
                out[node.targets[0].id] = ast.literal_eval(node.value)
            except ValueError:
                pass
    return out


def test_launch_file_names_what_the_package_has():
    c = _constants()
    scripts = re.findall(r"'([\w-]+) = gcn_match_ros\.[\w.]+:main'", (REPO / "setup.py").read_text())
    assert c["PACKAGE"] == "gcn_match_ros"
    assert {c["FEATURE_EXECUTABLE"], c["MATCHER_EXECUTABLE"]} <= set(scripts)
    assert (REPO / c["DEFAULT_PARAMS_FILE"]).is_file()
    feature_src = (REPO / "gcn_match_ros" / "ros" / "feature_node.py").read_text()
    for name in c["FEATURE_PARAMETERS"]:
        assert f'declare_parameter("{name}"' in feature_src, name
    from gcn_match_ros.ros.parameters import MATCHER_PARAMETERS

    assert set(c["MATCHER_PARAMETERS"]) <= {p.name for p in MATCHER_PARAMETERS}
    assert set(c["ARGUMENTS"]) == {"cameras", "namespace", "params_file", "detector", "image_topic"}
    # the feature node reads "image" (remapped to image_topic) and publishes "keypoints", which
    # the matcher subscribes as <camera>/keypoints
    assert 'create_subscription(Image, "image"' in feature_src and '"keypoints"' in feature_src


def test_setup_installs_the_launch_and_parameter_files():
    text = (REPO / "setup.py").read_text()
    assert "'launch', '*.launch.py'" in text and "'config', '*.yaml'" in text
