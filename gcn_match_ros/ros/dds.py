"""Fast DDS and large Keypoints messages; the environment of a session kept on this machine.

Fast DDS carries same-host traffic through a shared-memory segment of 512 KiB per
participant by default. A process that publishes several cameras' Keypoints at once
(bag replay, a benchmark, a multi-camera driver) — or one frame larger than the segment
(1000 SIFT keypoints = 512 KB) — overflows it: measured here with 4 × 256 KB frames per
capture, a best-effort subscriber lost about half of one camera's frames and a reliable
one got them up to 0.9 s late (retransmissions). A larger segment removes both.
:func:`use_large_shm` writes a Fast DDS profile that adds a shared-memory transport with a
larger segment and points ``FASTRTPS_DEFAULT_PROFILES_FILE`` at it (unless the user has
a profile of their own). It only adds a same-host transport: with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` the rmw still configures discovery and UDP
as before, so nothing more leaves the machine. The publishing process must have it set
before its first ``rclpy.init`` (the segment is the writer's). :func:`local_session_env` is the
environment of a process that starts ROS processes of its own (the demo, the node benchmark):
the large segment, this machine only, a domain and a log directory.
"""
from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path
from typing import Dict, MutableMapping, Optional, Tuple

__all__ = ["FASTDDS_PROFILE_ENV", "large_shm_profile", "local_session_env", "use_large_shm"]

#: Environment variable Fast DDS (2.x, ROS 2 Jazzy) reads its default XML profile from.
FASTDDS_PROFILE_ENV = "FASTRTPS_DEFAULT_PROFILES_FILE"

_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- Written by gcn_match_ros.ros.dds.large_shm_profile: a shared-memory transport with a
     {mb} MiB segment, so several large Keypoints messages fit in flight at once. -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>gcn_match_ros_shm</transport_id>
      <type>SHM</type>
      <segment_size>{size}</segment_size>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="gcn_match_ros_large_shm" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>gcn_match_ros_shm</transport_id>
      </userTransports>
    </rtps>
  </participant>
</profiles>
"""


def large_shm_profile(segment_mb: int = 16, directory: Optional[Path] = None) -> Path:
    """Write (once) the Fast DDS profile with a ``segment_mb`` MiB shared-memory segment;
    returns its path (in ``directory``, default the temporary directory)."""
    directory = Path(directory or tempfile.gettempdir())
    path = directory / f"gcn_match_ros-fastdds-shm-{int(segment_mb)}mb-{os.getuid()}.xml"
    text = _PROFILE.format(mb=int(segment_mb), size=int(segment_mb) * 1024 * 1024)
    if not path.is_file() or path.read_text() != text:
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=".gcn_match_ros-fastdds-", suffix=".xml")
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    return path


def use_large_shm(env: Optional[MutableMapping[str, str]] = None, segment_mb: int = 16) -> Optional[Path]:
    """Point ``env`` (default ``os.environ``) at :func:`large_shm_profile` unless it already
    names a Fast DDS profile; returns the profile set, or None when left as it was."""
    env = os.environ if env is None else env
    if env.get(FASTDDS_PROFILE_ENV) or env.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        return None
    path = large_shm_profile(segment_mb)
    env[FASTDDS_PROFILE_ENV] = str(path)
    return path


def local_session_env(log_prefix: str, large_shm: bool = True) -> Tuple[Dict[str, str], int]:
    """The environment for ROS processes this one starts, and this one's own (set here, so before
    its ``rclpy.init``): ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (no traffic leaves the machine;
    the deprecated ``ROS_LOCALHOST_ONLY`` removed), ``ROS_DOMAIN_ID`` as set, else a random domain
    1-100 of the session's own; ``ROS_LOG_DIR`` as set, else a new temporary directory whose name
    starts with ``log_prefix``; and, with ``large_shm``, the large shared-memory profile
    (:func:`use_large_shm`).

    Returns:
        (the child processes' environment, the domain id).
    """
    env = dict(os.environ)
    if large_shm:
        use_large_shm(env)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    domain = int(env.get("ROS_DOMAIN_ID") or random.SystemRandom().randint(1, 100))
    env["ROS_DOMAIN_ID"] = str(domain)
    if not env.get("ROS_LOG_DIR"):
        env["ROS_LOG_DIR"] = tempfile.mkdtemp(prefix=log_prefix)
    own = ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID", "ROS_LOG_DIR")
    os.environ.update({k: env[k] for k in own + ((FASTDDS_PROFILE_ENV,) if env.get(FASTDDS_PROFILE_ENV) else ())})
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    return env, domain
