"""The rosbags type store: standard ROS 2 Jazzy types plus ``gcn_match_msgs``, read from the
``.msg`` files (installed share dirs first, else the source tree's ``msg_defs/msg``), so
bags are written and read without rclpy or a ROS install.
"""
from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import List, Tuple

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.interfaces import Nodetype

from ..paths import CHECKOUT

__all__ = ["BagError", "MSG_PACKAGE", "KEYPOINTS_TYPE", "LABELS_TYPE", "MATCH_WINDOW_TYPE", "CAMERA_INFO_TYPE",
           "POSE_TYPE", "HEADER_TYPE", "typestore", "ensure_type", "find_msg_file", "normalise_type", "has_header"]

MSG_PACKAGE = "gcn_match_msgs"
OUR_TYPES = ("Keypoints", "MatchWindow", "KeypointLabels")
KEYPOINTS_TYPE = "gcn_match_msgs/msg/Keypoints"
LABELS_TYPE = "gcn_match_msgs/msg/KeypointLabels"
MATCH_WINDOW_TYPE = "gcn_match_msgs/msg/MatchWindow"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
POSE_TYPE = "geometry_msgs/msg/PoseStamped"
HEADER_TYPE = "std_msgs/msg/Header"
_SRC_MSG_DIR = CHECKOUT / "msg_defs" / "msg"


class BagError(ValueError):
    """A bag that cannot be read or written (missing, truncated, corrupt, wrong types);
    the message names the file."""



def _share_msg_dirs(package: str) -> List[Path]:
    """``<prefix>/share/<package>/msg`` for every prefix on AMENT_PREFIX_PATH, then the
    interpreter's prefix (the venv the message package was installed into)."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    prefixes += [sys.prefix]
    dirs: List[Path] = []
    for p in prefixes:
        d = Path(p) / "share" / package / "msg"
        if d.is_dir() and d not in dirs:
            dirs.append(d)
    return dirs


def find_msg_file(msgtype: str) -> Path:
    """The ``.msg`` file of ``pkg/msg/Name``: an installed share dir first (what the
    generated rclpy classes were built from), then, for gcn_match_msgs, the source tree's
    ``msg_defs/msg``.

    Raises:
        BagError: no such file anywhere.
    """
    pkg, _, name = _split_type(msgtype)
    dirs = _share_msg_dirs(pkg)
    if pkg == MSG_PACKAGE:
        dirs.append(_SRC_MSG_DIR)
    for d in dirs:
        f = d / f"{name}.msg"
        if f.is_file():
            return f
    raise BagError(f"no definition of {msgtype}: {name}.msg not found in "
                   f"{[str(d) for d in dirs] or 'any share/' + pkg + '/msg (is AMENT_PREFIX_PATH set?)'}")


def _split_type(msgtype: str) -> Tuple[str, str, str]:
    parts = msgtype.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(parts):
        raise BagError(f"not a message type name (pkg/msg/Name): {msgtype!r}")
    return parts[0], parts[1], parts[2]


def ensure_type(store, msgtype: str) -> str:
    """Register ``msgtype`` (and the types it uses) in ``store`` from installed ``.msg``
    files if it is not known yet; returns the normalised name ``pkg/msg/Name``."""
    pkg, kind, name = _split_type(msgtype)
    full = f"{pkg}/{kind}/{name}"
    if full in store.fielddefs:
        return full
    types = get_types_from_msg(find_msg_file(full).read_text(), full)
    store.register(types)
    for _, (_, fields) in types.items():
        for _, (nodetype, spec) in fields:
            for ref in _referenced(nodetype, spec):
                ensure_type(store, ref)
    return full


def _referenced(nodetype, spec) -> List[str]:
    """Message type names a field definition refers to."""
    if nodetype == Nodetype.NAME:
        return [spec]
    if nodetype in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        (sub_type, sub_spec), _ = spec
        return _referenced(sub_type, sub_spec)
    return []


@functools.lru_cache(maxsize=None)
def typestore():
    """The rosbags type store for ROS 2 Jazzy with gcn_match_msgs registered (shared,
    cached: do not register conflicting definitions in it)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for name in OUR_TYPES:
        full = f"{MSG_PACKAGE}/msg/{name}"
        types.update(get_types_from_msg(find_msg_file(full).read_text(), full))
    store.register(types)
    return store



def has_header(msgtype: str, store=None) -> bool:
    """True when the type's first field is a ``std_msgs/msg/Header`` (restampable)."""
    store = store or typestore()
    try:
        ensure_type(store, msgtype)
    except BagError:
        return False
    fields = store.fielddefs[normalise_type(msgtype)][1]
    return bool(fields) and fields[0][1][1] == HEADER_TYPE


def normalise_type(msgtype: str) -> str:
    """``pkg/Name`` or ``pkg/msg/Name`` -> ``pkg/msg/Name``."""
    pkg, kind, name = _split_type(msgtype)
    return f"{pkg}/{kind}/{name}"

