"""Tests of gcn_match_ros.ros.dds: the large shared-memory Fast DDS profile, the environment pointing at it,
and a local session's environment."""
import os
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from gcn_match_ros.ros.dds import FASTDDS_PROFILE_ENV, large_shm_profile, local_session_env, use_large_shm

NS = "{http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles}"


def test_large_shm_profile_is_written_once_with_the_segment_size(tmp_path):
    path = large_shm_profile(8, directory=tmp_path)
    assert path.parent == tmp_path and path.name == f"gcn_match_ros-fastdds-shm-8mb-{os.getuid()}.xml"
    root = ET.parse(path).getroot()  # well-formed XML
    assert root.find(f".//{NS}segment_size").text == str(8 * 1024 * 1024)
    assert root.find(f".//{NS}type").text == "SHM"
    assert root.find(f".//{NS}participant").get("is_default_profile") == "true"
    # the same profile again: the file is left as it is
    stat = path.stat()
    assert large_shm_profile(8, directory=tmp_path) == path
    assert path.stat().st_ino == stat.st_ino and path.stat().st_mtime_ns == stat.st_mtime_ns
    # a file with other content (e.g. an older version) is rewritten
    path.write_text("<profiles/>")
    assert large_shm_profile(8, directory=tmp_path) == path
    assert f"<segment_size>{8 * 1024 * 1024}</segment_size>" in path.read_text()
    # another size is another file; no temporary files are left behind
    other = large_shm_profile(32, directory=tmp_path)
    assert other != path and f"<segment_size>{32 * 1024 * 1024}</segment_size>" in other.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([path.name, other.name])


@pytest.fixture
def temp_dir(tmp_path, monkeypatch):
    """The temporary directory (where use_large_shm writes its profile) is tmp_path."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    return tmp_path


def test_use_large_shm_points_an_environment_at_the_profile(temp_dir):
    env = {"PATH": "/usr/bin"}
    path = use_large_shm(env, segment_mb=4)
    assert path == temp_dir / f"gcn_match_ros-fastdds-shm-4mb-{os.getuid()}.xml" and path.is_file()
    assert env == {"PATH": "/usr/bin", FASTDDS_PROFILE_ENV: str(path)}
    assert FASTDDS_PROFILE_ENV == "FASTRTPS_DEFAULT_PROFILES_FILE"
    assert f"<segment_size>{4 * 1024 * 1024}</segment_size>" in path.read_text()


@pytest.mark.parametrize("name", ["FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"])
def test_use_large_shm_leaves_a_users_profile_alone(temp_dir, name):
    env = {name: "/home/me/my_profile.xml"}
    assert use_large_shm(env) is None
    assert env == {name: "/home/me/my_profile.xml"}
    assert list(temp_dir.iterdir()) == []  # nothing written


def test_use_large_shm_defaults_to_os_environ(temp_dir, monkeypatch):
    for name in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        monkeypatch.setenv(name, "")  # recorded, so the environment is restored after the test
        monkeypatch.delenv(name)
    path = use_large_shm()
    assert os.environ[FASTDDS_PROFILE_ENV] == str(path) and path.parent == temp_dir


SESSION_KEYS = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY", "ROS_DOMAIN_ID", "ROS_LOG_DIR",
                "FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


@pytest.fixture
def session_environ(temp_dir, monkeypatch):
    """os.environ without the session's variables (restored after the test)."""
    for name in SESSION_KEYS:
        monkeypatch.setenv(name, "")  # recorded, so the environment is restored after the test
        monkeypatch.delenv(name)
    return temp_dir


def test_local_session_env_keeps_what_is_set_and_creates_nothing(session_environ, monkeypatch):
    monkeypatch.setenv("ROS_DOMAIN_ID", "42")
    monkeypatch.setenv("ROS_LOG_DIR", "/var/log/mine")
    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")
    env, domain = local_session_env("gcn_match_ros-test-", large_shm=False)
    assert domain == 42 and env["ROS_DOMAIN_ID"] == "42" and env["ROS_LOG_DIR"] == "/var/log/mine"
    assert env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST" and "ROS_LOCALHOST_ONLY" not in env
    assert FASTDDS_PROFILE_ENV not in env
    assert list(session_environ.iterdir()) == []  # no log directory, no profile
    # this process's own environment is the same
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST" and "ROS_LOCALHOST_ONLY" not in os.environ
    assert os.environ["ROS_DOMAIN_ID"] == "42" and os.environ["ROS_LOG_DIR"] == "/var/log/mine"


def test_local_session_env_fills_in_a_domain_a_log_directory_and_the_profile(session_environ):
    env, domain = local_session_env("gcn_match_ros-test-")
    assert 1 <= domain <= 100 and env["ROS_DOMAIN_ID"] == os.environ["ROS_DOMAIN_ID"] == str(domain)
    log_dir = Path(env["ROS_LOG_DIR"])
    assert log_dir.is_dir() and log_dir.parent == session_environ and log_dir.name.startswith("gcn_match_ros-test-")
    assert os.environ["ROS_LOG_DIR"] == str(log_dir)
    profile = Path(env[FASTDDS_PROFILE_ENV])
    assert profile.parent == session_environ and os.environ[FASTDDS_PROFILE_ENV] == str(profile)
    assert sorted(p.name for p in session_environ.iterdir()) == sorted([log_dir.name, profile.name])
