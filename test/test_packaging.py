"""Packaging: the generated messages work from the venv, and a colcon build of the
workspace yields exactly the layout `ros2 run gcn_match_ros <exe>` resolves."""
from __future__ import annotations

import array
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
PKG = "gcn_match_ros"
EXECUTABLES = {  # console script -> module:function (must match setup.py)
    "gcn-match": "gcn_match_ros.cli:main",
    "matcher_node": "gcn_match_ros.ros.matcher_node:main",
    "lifecycle_matcher_node": "gcn_match_ros.ros.matcher_node:lifecycle_main",
    "feature_node": "gcn_match_ros.ros.feature_node:main",
    "visualizer_node": "gcn_match_ros.ros.visualizer_node:main",
    "mapping_node": "gcn_match_ros.ros.mapping_node:main",
    "bag_play": "gcn_match_ros.ros.bag_play:main",
    "bag_record": "gcn_match_ros.ros.bag_record:main",
    "match_consumer": "gcn_match_ros.ros.example_consumer:main",
}
COLCON_TIMEOUT_S = 240


def _f32(a) -> array.array:
    return array.array("f", np.ascontiguousarray(a, np.float32).tobytes())


def _u32(a) -> array.array:
    return array.array("I", np.ascontiguousarray(a, np.uint32).tobytes())


def _roundtrip(msg):
    from rclpy.serialization import deserialize_message, serialize_message
    return deserialize_message(serialize_message(msg), type(msg))


def test_keypoints_roundtrip_float_and_binary():
    from gcn_match_msgs.msg import Keypoints

    assert (Keypoints.DESCRIPTOR_FLOAT, Keypoints.DESCRIPTOR_BINARY) == (0, 1)
    rng = np.random.default_rng(0)
    n, d = 500, 128
    kps = rng.uniform(0, 640, size=(n, 2)).astype(np.float32)
    desc = rng.normal(size=(n, d)).astype(np.float32)

    m = Keypoints()
    m.header.frame_id = "cam0_optical"
    m.header.stamp.sec, m.header.stamp.nanosec = 12, 345
    m.camera_id = "cam0"
    m.camera_info.width, m.camera_info.height = 640, 480
    m.camera_info.k = [500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0]
    m.count = n
    m.keypoints = _f32(kps)
    m.scales = _f32(np.full(n, 2.0))
    m.orientations = _f32(np.linspace(-np.pi, np.pi, n))
    m.scores = _f32(np.linspace(0, 1, n))
    m.descriptor_type = Keypoints.DESCRIPTOR_FLOAT
    m.descriptor_name = "sift"
    m.descriptor_dim = d
    m.descriptors = _f32(desc)

    r = _roundtrip(m)
    assert (r.camera_id, r.header.frame_id, r.header.stamp.sec, r.header.stamp.nanosec) == \
        ("cam0", "cam0_optical", 12, 345)
    assert (r.camera_info.width, r.camera_info.height) == (640, 480)
    assert np.allclose(np.asarray(r.camera_info.k).reshape(3, 3)[0], [500, 0, 320])
    assert r.count == n and r.descriptor_dim == d and r.descriptor_name == "sift"
    np.testing.assert_array_equal(np.frombuffer(r.keypoints, np.float32).reshape(n, 2), kps)
    np.testing.assert_array_equal(np.frombuffer(r.descriptors, np.float32).reshape(n, d), desc)
    assert len(r.scales) == len(r.orientations) == len(r.scores) == n
    assert len(r.descriptors_binary) == 0

    # ORB-like binary descriptors: 256 bits -> 32 packed bytes per keypoint.
    bits = rng.integers(0, 2, size=(n, 256), dtype=np.uint8)
    packed = np.packbits(bits, axis=1)
    b = Keypoints(count=n, keypoints=_f32(kps), descriptor_type=Keypoints.DESCRIPTOR_BINARY,
                  descriptor_name="orb", descriptor_dim=256)
    b.descriptors_binary = array.array("B", packed.tobytes())
    rb = _roundtrip(b)
    assert rb.descriptor_type == Keypoints.DESCRIPTOR_BINARY and len(rb.descriptors) == 0
    got = np.frombuffer(rb.descriptors_binary, np.uint8).reshape(n, -1)
    np.testing.assert_array_equal(np.unpackbits(got, axis=1), bits)


def test_match_window_roundtrip():
    from builtin_interfaces.msg import Time
    from gcn_match_msgs.msg import MatchWindow

    offsets = np.array([0, 4, 9, 12], np.uint32)
    n = int(offsets[-1])
    rows = np.array([0, 1, 4, 5], np.uint32)
    cols = np.array([4, 9, 9, 10], np.uint32)
    scores = np.array([0.9, 0.8, 0.7, 0.6], np.float32)
    dense = np.zeros((n, n), np.float32)
    dense[rows, cols] = scores
    track = np.full(n, -1, np.int32)
    track[[0, 4]] = 0
    track[[1, 9]] = 1

    m = MatchWindow()
    m.header.stamp.sec = 7
    m.camera_ids = ["cam0", "cam1", "cam2"]
    m.frame_ids = ["cam0_optical", "cam1_optical", "cam2_optical"]
    m.view_stamps = [Time(sec=7, nanosec=i) for i in range(3)]
    m.view_offsets = _u32(offsets)
    m.pair_rows, m.pair_cols, m.pair_scores = _u32(rows), _u32(cols), _f32(scores)
    m.score_threshold = 0.5
    m.dense_scores = _f32(dense)
    m.track = array.array("i", track.tobytes())
    m.track_count = 2
    m.method = "gcn:default.pt"
    m.build_seconds, m.solve_seconds, m.total_seconds, m.latency_seconds = 0.01, 0.02, 0.04, 0.05

    r = _roundtrip(m)
    assert list(r.camera_ids) == m.camera_ids and list(r.frame_ids) == m.frame_ids
    assert [t.nanosec for t in r.view_stamps] == [0, 1, 2]
    np.testing.assert_array_equal(np.frombuffer(r.view_offsets, np.uint32), offsets)
    np.testing.assert_array_equal(np.frombuffer(r.pair_rows, np.uint32), rows)
    np.testing.assert_array_equal(np.frombuffer(r.pair_cols, np.uint32), cols)
    np.testing.assert_array_equal(np.frombuffer(r.pair_scores, np.float32), scores)
    np.testing.assert_array_equal(np.frombuffer(r.dense_scores, np.float32).reshape(n, n), dense)
    np.testing.assert_array_equal(np.frombuffer(r.track, np.int32), track)
    assert (r.track_count, r.method) == (2, "gcn:default.pt")
    assert r.score_threshold == pytest.approx(0.5)
    assert r.latency_seconds == pytest.approx(0.05)


def test_msg_definitions_parse_with_rosbags():
    """The .msg files (with their comments) load into a rosbags typestore, and rosbags'
    CDR bytes decode with rclpy: what the bag tools rely on."""
    from rclpy.serialization import deserialize_message
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from gcn_match_msgs.msg import Keypoints

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in ("Keypoints", "MatchWindow"):
        text = (REPO / "msg_defs" / "msg" / f"{name}.msg").read_text()
        types.update(get_types_from_msg(text, f"gcn_match_msgs/msg/{name}"))
    store.register(types)
    K = store.types["gcn_match_msgs/msg/Keypoints"]
    assert K.DESCRIPTOR_BINARY == 1
    T = store.types
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=2),
                                      frame_id="cam1_optical")
    info = T["sensor_msgs/msg/CameraInfo"](
        header=header, height=480, width=640, distortion_model="", d=np.zeros(0),
        k=np.zeros(9), r=np.zeros(9), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                  do_rectify=False))
    kps = np.arange(6, dtype=np.float32)
    msg = K(header=header, camera_id="cam1", camera_info=info, count=3, keypoints=kps,
            scales=np.zeros(0, np.float32), orientations=np.zeros(0, np.float32),
            scores=np.zeros(0, np.float32), descriptor_type=0, descriptor_name="sift",
            descriptor_dim=2, descriptors=np.ones(6, np.float32),
            descriptors_binary=np.zeros(0, np.uint8))
    raw = bytes(store.serialize_cdr(msg, "gcn_match_msgs/msg/Keypoints"))
    r = deserialize_message(raw, Keypoints)
    assert (r.camera_id, r.count, r.camera_info.width) == ("cam1", 3, 640)
    np.testing.assert_array_equal(np.frombuffer(r.keypoints, np.float32), kps)


@pytest.mark.timeout(COLCON_TIMEOUT_S + 30)
def test_colcon_build_ros2_run_layout(tmp_path, monkeypatch):
    colcon = shutil.which("colcon", path=str(Path(sys.executable).parent)) or shutil.which("colcon")
    if colcon is None:
        pytest.fail("colcon not found: run ./run.sh setup (installs colcon-common-extensions)")
    prefix = sys.prefix  # the venv: the pip-installed ROS packages live here
    env = dict(os.environ)
    env.update(AMENT_PREFIX_PATH=prefix, CMAKE_PREFIX_PATH=prefix, VIRTUAL_ENV=prefix,
               PATH=str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", ""),
               PYTHONDONTWRITEBYTECODE="1")
    install = tmp_path / "install"
    # msg_defs/ sits inside the gcn_match_ros package directory, and colcon does not
    # descend into a package, so both paths are given.
    cmd = [colcon, "--log-base", str(tmp_path / "log"), "build",
           "--base-paths", str(REPO), str(REPO / "msg_defs"),
           "--build-base", str(tmp_path / "build"), "--install-base", str(install),
           "--event-handlers", "console_direct-", "console_cohesion-", "status-",
           "desktop_notification-", "terminal_title-",
           "--cmake-args", f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"]
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tmp_path,
                              timeout=COLCON_TIMEOUT_S)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"colcon build exceeded {COLCON_TIMEOUT_S} s:\n{e.stdout}\n{e.stderr}")
    assert proc.returncode == 0, f"colcon build failed:\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    assert "2 packages finished" in proc.stdout, proc.stdout

    # What `ros2 run gcn_match_ros EXE` does: find a prefix on AMENT_PREFIX_PATH holding
    # share/ament_index/resource_index/packages/gcn_match_ros, then run <prefix>/lib/gcn_match_ros/EXE.
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    pkg_prefix, msgs_prefix = install / PKG, install / "gcn_match_msgs"
    monkeypatch.setenv("AMENT_PREFIX_PATH", os.pathsep.join([str(pkg_prefix), str(msgs_prefix)]))
    assert Path(get_package_prefix(PKG)) == pkg_prefix
    assert Path(get_package_prefix("gcn_match_msgs")) == msgs_prefix
    assert (pkg_prefix / "share/ament_index/resource_index/packages" / PKG).is_file()
    share = Path(get_package_share_directory(PKG))
    assert (share / "package.xml").is_file()
    # parameter files and the launch file, where `ros2 launch` / --params-file users find them
    assert {p.name for p in (share / "config").glob("*.yaml")} == {p.name for p in (REPO / "config").glob("*.yaml")}
    assert (share / "launch" / "gcn_match.launch.py").is_file()
    libdir = pkg_prefix / "lib" / PKG
    for exe, target in EXECUTABLES.items():
        path = libdir / exe
        assert path.is_file() and os.access(path, os.X_OK), f"missing executable {path}"
        text = path.read_text()
        assert text.startswith("#!") and "python" in text.splitlines()[0], text[:200]
        assert f"'{exe}'" in text, f"{path} is not the console script {exe}"
    assert sorted(p.name for p in libdir.iterdir() if p.is_file()) == sorted(EXECUTABLES)

    site = pkg_prefix / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
    assert (site / PKG / "__init__.py").is_file()
    for model in (REPO / PKG / "models").glob("*"):  # package_data ships with the package
        if model.suffix in (".pt", ".json"):
            assert (site / PKG / "models" / model.name).is_file(), model
    for f in (REPO / "bags").rglob("*"):
        if f.is_file() and not f.name.startswith("."):
            assert (pkg_prefix / "share" / PKG / f.relative_to(REPO)).is_file(), f

    # The message package colcon built works from its own (non-venv) prefix.
    msgs_site = msgs_prefix / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
    check = ("import array, gcn_match_msgs.msg as m;"
             "from rclpy.serialization import serialize_message as s, deserialize_message as d;"
             "k = m.Keypoints(count=1, keypoints=array.array('f', [1.0, 2.0]));"
             "assert list(d(s(k), m.Keypoints).keypoints) == [1.0, 2.0];"
             "print(m.__file__)")
    env2 = dict(env, PYTHONPATH=str(msgs_site),
                LD_LIBRARY_PATH=os.pathsep.join(filter(None, [str(msgs_prefix / "lib"),
                                                              os.environ.get("LD_LIBRARY_PATH")])))
    out = subprocess.run([sys.executable, "-c", check], env=env2, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().startswith(str(msgs_site)), out.stdout


#: Third-party top-level modules of the package -> how package.xml declares them (rosdep key,
#: or "pip:" for a documented pip dependency without a key).
_RUNTIME_DEPENDENCIES = {
    "numpy": "python3-numpy", "cv2": "python3-opencv", "scipy": "python3-scipy", "numba": "python3-numba",
    "llvmlite": "python3-numba",  # numba's own dependency, installed with it
    "threadpoolctl": "python3-threadpoolctl", "torch": "python3-torch",
    "matplotlib": "python3-matplotlib", "tqdm": "python3-tqdm", "rosbags": "pip:rosbags",
    "rclpy": "rclpy", "rcl_interfaces": "rcl_interfaces", "std_msgs": "std_msgs", "sensor_msgs": "sensor_msgs",
    "geometry_msgs": "geometry_msgs", "diagnostic_msgs": "diagnostic_msgs",
    "builtin_interfaces": "builtin_interfaces", "gcn_match_msgs": "gcn_match_msgs",
    "ament_index_python": "ament_index_python",
}


def test_package_xml_declares_every_runtime_dependency():
    import ast
    import sys
    import xml.etree.ElementTree as ET

    package_dir = REPO / "gcn_match_ros"
    imported = set()
    for path in package_dir.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                imported.add(node.module.split(".")[0])
    third_party = imported - set(sys.stdlib_module_names) - {"gcn_match_ros", "__future__"}
    unknown = third_party - set(_RUNTIME_DEPENDENCIES)
    assert not unknown, f"imports without a declared dependency: {sorted(unknown)}"
    text = (REPO / "package.xml").read_text()
    declared = {e.text for e in ET.fromstring(text).iter() if e.tag in ("exec_depend", "depend")}
    for module in sorted(third_party):
        key = _RUNTIME_DEPENDENCIES[module]
        if key.startswith("pip:"):
            assert f"pip install {key[4:]}" in text, f"{module}: pip dependency not documented in package.xml"
        else:
            assert key in declared, f"{module}: package.xml lacks <exec_depend>{key}</exec_depend>"
