"""Tests of gcn_match_ros.ros.parameters: the matcher node's parameter table and its ROS descriptors (no DDS)."""
import dataclasses
import time

import pytest
import torch
from rcl_interfaces.msg import ParameterType

from gcn_match_ros.ros.parameters import INPUT_QOS, MATCHER_PARAMETERS, WINDOW_PARAMETER_NAMES, ParameterSpec
from gcn_match_ros.windowing import WindowConfig, window_parameters

TYPE_OF_DEFAULT = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
                   float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
                   list: ParameterType.PARAMETER_STRING_ARRAY}


def test_parameter_names_are_unique():
    names = [p.name for p in MATCHER_PARAMETERS]
    assert len(names) == len(set(names))


def test_window_parameters_are_window_config_fields_with_its_defaults():
    by_name = {p.name: p for p in MATCHER_PARAMETERS}
    window = window_parameters()
    assert WINDOW_PARAMETER_NAMES == tuple(w.name for w in window)
    assert set(WINDOW_PARAMETER_NAMES) <= {f.name for f in dataclasses.fields(WindowConfig)}
    defaults = WindowConfig(cameras=("cam0", "cam1"))
    for w in window:
        spec = by_name[w.name]
        assert spec.default == w.default == getattr(defaults, w.name), w.name
        assert type(spec.default) is type(getattr(defaults, w.name)), w.name  # 1 is no 1.0: the ROS type
        assert (spec.description, spec.low, spec.high, spec.constraints) == (w.doc, w.low, w.high, w.constraints)
        assert not spec.read_only  # window settings may change at run time
    # declared right after the cameras, in WindowConfig's order
    assert [p.name for p in MATCHER_PARAMETERS[1:1 + len(window)]] == list(WINDOW_PARAMETER_NAMES)


@pytest.mark.parametrize("spec", MATCHER_PARAMETERS, ids=lambda s: s.name)
def test_descriptor_has_the_type_and_range_of_the_spec(spec):
    d = spec.descriptor()
    assert d.type == TYPE_OF_DEFAULT[type(spec.default)]
    assert d.read_only == spec.read_only and d.description == spec.description
    assert d.additional_constraints == spec.constraints
    if spec.low is None:
        assert len(d.integer_range) == 0 and len(d.floating_point_range) == 0
    elif isinstance(spec.default, int):
        (r,) = d.integer_range
        assert (r.from_value, r.to_value, r.step) == (spec.low, spec.high, 1) and len(d.floating_point_range) == 0
        assert spec.low <= spec.default <= spec.high
    else:
        (r,) = d.floating_point_range
        assert (r.from_value, r.to_value, r.step) == (spec.low, spec.high, 0.0) and len(d.integer_range) == 0
        assert spec.low <= spec.default <= spec.high


def test_node_parameters_name_their_choices():
    by_name = {p.name: p for p in MATCHER_PARAMETERS}
    assert by_name["input_qos"].default in INPUT_QOS
    assert "gcn" in by_name["solver"].description and "nn-ransac" in by_name["solver"].description
    assert by_name["cameras"].read_only and len(set(by_name["cameras"].default)) >= 2


def test_a_bool_parameter_has_no_range():
    with pytest.raises(ValueError, match="flag: a bool parameter has no range"):
        ParameterSpec("flag", True, "a flag", low=0, high=1).descriptor()


# ---------------------------------------------------------------------------------------
# Parameter files (config/): the node starts from each and its parameters take the values
# ---------------------------------------------------------------------------------------
import uuid  # noqa: E402
from pathlib import Path  # noqa: E402

import yaml  # noqa: E402

from gcn_match_ros.ros.parameters import params_yaml  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "config"


def test_matcher_yaml_is_every_parameter_at_its_default():
    """config/matcher.yaml is generated from the parameter table (one owner); regenerate with
    ``python -c "from gcn_match_ros.ros.parameters import params_yaml; print(params_yaml(), end='')" > config/matcher.yaml``."""
    assert (CONFIG / "matcher.yaml").read_text() == params_yaml()
    values = yaml.safe_load(params_yaml())["/**/matcher_node"]["ros__parameters"]
    assert values == {spec.name: spec.default for spec in MATCHER_PARAMETERS}


@pytest.mark.parametrize("name", sorted(p.name for p in CONFIG.glob("*.yaml")))
def test_the_node_starts_from_each_parameter_file(name):
    from gcn_match_ros.ros.matcher_node import PER_WINDOW, MatcherNode
    from conftest import domain_id, second_thread_cpus
    from gcn_match_ros.ros.testing import RosSession

    wanted = yaml.safe_load((CONFIG / name).read_text())["/**/matcher_node"]["ros__parameters"]
    assert set(wanted) <= {spec.name for spec in MATCHER_PARAMETERS}, "unknown parameters in the file"
    torch_threads = torch.get_num_threads()
    second_cpus = second_thread_cpus()
    with RosSession("tester", domain_id=domain_id()) as session:
        node = MatcherNode(context=session.context, namespace=f"/t{uuid.uuid4().hex[:10]}",
                           cli_args=["--ros-args", "--params-file", str(CONFIG / name)])
        try:
            got = {k: node.get_parameter(k).value for k in wanted}
            assert got == wanted
            assert node._method.startswith(wanted.get("solver", "gcn").split(":")[0])
            if wanted.get("cpu_affinity", -1) >= 0:  # the worker has pinned the threads
                deadline = time.monotonic() + 10
                while node._solve_cpus == PER_WINDOW and time.monotonic() < deadline:
                    time.sleep(0.01)
                assert node._solve_cpus != PER_WINDOW
        finally:
            assert node.stop()
            node.destroy_node()
    # a stopped node leaves this process's threads as they were (config/pinned.yaml pins them)
    assert torch.get_num_threads() == torch_threads
    assert second_thread_cpus() == second_cpus
