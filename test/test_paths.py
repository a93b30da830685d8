"""Tests of gcn_match_ros.paths: the one owner of where a checkout's files are."""
from pathlib import Path

import gcn_match_ros
from gcn_match_ros.paths import CHECKOUT


def test_checkout_is_the_directory_holding_the_package():
    assert CHECKOUT / "gcn_match_ros" == Path(gcn_match_ros.__file__).resolve().parent
    # the tests run from a source checkout: its files lie beside the package
    for name in ("setup.py", "package.xml", "config/matcher.yaml", "msg_defs/msg/MatchWindow.msg", "bags"):
        assert (CHECKOUT / name).exists(), name


def test_readers_take_their_files_from_it():
    from gcn_match_ros.bags.typesys import find_msg_file
    from gcn_match_ros.data.scenes import DATA_ROOT
    from gcn_match_ros.experiments import command_line

    assert DATA_ROOT == CHECKOUT.parent / "shared" / "data"
    assert find_msg_file("gcn_match_msgs/msg/MatchWindow").name == "MatchWindow.msg"
    # a benchmark's command is shown relative to the checkout
    assert command_line(CHECKOUT / "benchmarks" / "real_eval.py", ["--quick"]) == ".venv/bin/python benchmarks/real_eval.py --quick"
