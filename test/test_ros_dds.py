"""Tests of gcn_match_ros.ros.dds: the large shared-memory Fast DDS profile and the environment pointing at it."""
import os
import tempfile
import xml.etree.ElementTree as ET

import pytest

from gcn_match_ros.ros.dds import FASTDDS_PROFILE_ENV, large_shm_profile, use_large_shm

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
