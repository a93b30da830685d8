"""Tests of gcn_match_ros.bags.typesys: the type store holds the installed gcn_match_msgs definitions."""
from __future__ import annotations

from gcn_match_ros.bags import typesys

from conftest import REPO


def test_typestore_matches_installed_messages():
    store = typesys.typestore()
    T = store.types[typesys.LABELS_TYPE]
    assert (T.UNMATCHED, T.UNLABELLED) == (-1, -2)
    for name in typesys.OUR_TYPES:  # a stale message build would decode bags differently
        src = (REPO / "msg_defs" / "msg" / f"{name}.msg").read_text()
        assert typesys.find_msg_file(f"gcn_match_msgs/msg/{name}").read_text() == src, \
            f"installed {name}.msg differs from msg_defs/: run ./run.sh setup"
