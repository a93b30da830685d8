"""The matcher node's parameters as data: name, default, description, range, read-only.

The window parameters (``sync_tolerance``, ``max_delay``, ...) and their defaults come from
:class:`gcn_match_ros.windowing.WindowConfig` (:func:`~gcn_match_ros.windowing.window_parameters`),
the one place that also forms windows offline; the rest belong to the node. :func:`declare`
declares them on a node with ROS parameter descriptors (types, ranges, read-only), so invalid
values are refused by rclpy with a reason before the node sees them.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Optional, Tuple

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.node import Node

from ..solvers import available_solvers
from ..windowing import window_parameters

__all__ = ["ParameterSpec", "MATCHER_PARAMETERS", "WINDOW_PARAMETER_NAMES", "INPUT_QOS", "declare", "values",
           "params_yaml"]

#: Accepted values of the ``input_qos`` parameter.
INPUT_QOS = ("sensor_data", "reliable")


@dataclasses.dataclass(frozen=True)
class ParameterSpec:
    """One node parameter: its default decides its type; ``low``/``high`` bound numbers."""

    name: str
    default: Any
    description: str
    read_only: bool = False
    low: Optional[float] = None
    high: Optional[float] = None
    constraints: str = ""

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(description=self.description, read_only=self.read_only,
                                additional_constraints=self.constraints)
        d.type = _TYPES[type(self.default)]
        if self.low is not None and isinstance(self.default, bool):
            raise ValueError(f"{self.name}: a bool parameter has no range")
        if self.low is not None and isinstance(self.default, int):
            d.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=1)]
        elif self.low is not None:
            d.floating_point_range = [FloatingPointRange(from_value=float(self.low), to_value=float(self.high),
                                                         step=0.0)]
        return d


_TYPES = {bool: ParameterType.PARAMETER_BOOL, int: ParameterType.PARAMETER_INTEGER,
          float: ParameterType.PARAMETER_DOUBLE, str: ParameterType.PARAMETER_STRING,
          list: ParameterType.PARAMETER_STRING_ARRAY}

_WINDOW = tuple(ParameterSpec(p.name, p.default, p.doc, low=p.low, high=p.high, constraints=p.constraints)
                for p in window_parameters())
WINDOW_PARAMETER_NAMES = tuple(p.name for p in _WINDOW)

#: Every parameter of the matcher node, in declaration order.
MATCHER_PARAMETERS: Tuple[ParameterSpec, ...] = (
    ParameterSpec("cameras", ["cam0", "cam1", "cam2"],
                  "Camera ids, in window order; subscribes <camera>/keypoints for each.", read_only=True,
                  constraints="at least 2 distinct ids"),
    *_WINDOW,
    ParameterSpec("solver", "gcn", "Matching method, 'name' or 'name:key=value,...'; one of "
                                   f"{', '.join(available_solvers())}.", read_only=True),
    ParameterSpec("checkpoint", "", "GCN checkpoint file; empty: the model shipped in the package for each "
                                    "window's descriptors.", read_only=True),
    ParameterSpec("device", "cpu", "Torch device of the gcn solver: cpu, cuda or cuda:<index>.", read_only=True),
    ParameterSpec("score_threshold", 0.1, "Pairs scoring above it are listed in MatchWindow.pair_*.",
                  low=0.0, high=1.0),
    ParameterSpec("dense_output", False, "Also publish the dense N x N score matrix (windows up to 4096 keypoints)."),
    ParameterSpec("input_qos", "sensor_data", "QoS of the keypoint subscriptions: sensor_data (best effort, "
                                              "depth 5) or reliable (depth 10).", read_only=True,
                  constraints=" | ".join(INPUT_QOS)),
    ParameterSpec("landmarks", True, "Give every keypoint its persistent landmark id (MatchWindow.landmark_*); "
                                     "false: only the window's own tracks, without the association's cost.",
                  read_only=True),
    ParameterSpec("degrade_min_keypoints", 200, "Under load (windows superseded) solve fewer keypoints per view, "
                                                "the best-scored, down to this many, rather than only drop windows; "
                                                "back up when the worker keeps up; 0: never.", read_only=True,
                  low=0, high=100000),
    ParameterSpec("cpu_affinity", -1, "First of two CPUs for the solve, always: the worker thread runs on it "
                                      "and the solver's second thread on the next CPU this process may use "
                                      "(for CPUs set aside for the matcher); -1: the solver's own placement "
                                      "(gcn's keep_apart: for each window, the CPU the worker is on and the "
                                      "next, the OS placing both between windows). Either keeps a core for "
                                      "each where the kernel would pack the two onto one CPU after a pause "
                                      "between windows.",
                  read_only=True, low=-1, high=4095),
    ParameterSpec("keep_freed_memory", True, "Keep the memory a window frees for the next one (glibc's malloc "
                                             "thresholds, for this process): no page faults for the same arrays "
                                             "window after window; the resident memory stays at its peak.",
                  read_only=True),
    ParameterSpec("diagnostics_period", 1.0, "Period of /diagnostics reports [s].", read_only=True,
                  low=0.05, high=60.0),
)


def declare(node: Node, specs: Tuple[ParameterSpec, ...] = MATCHER_PARAMETERS) -> None:
    """Declare ``specs`` on ``node`` (overrides from the command line or a params file apply)."""
    for spec in specs:
        node.declare_parameter(spec.name, spec.default, spec.descriptor())


def values(node: Node, specs: Tuple[ParameterSpec, ...] = MATCHER_PARAMETERS) -> Dict[str, Any]:
    """The current value of every parameter of ``specs``."""
    return {spec.name: node.get_parameter(spec.name).value for spec in specs}


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace('\\', '\\\\').replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_yaml_value(v) for v in value) + "]"
    return repr(value)


def params_yaml(specs: Tuple[ParameterSpec, ...] = MATCHER_PARAMETERS, node: str = "matcher_node") -> str:
    """A ROS 2 parameter file of every parameter in ``specs`` at its default, each commented with
    its description, range and whether it is read-only: ``config/matcher.yaml`` is this text
    (a test keeps it so). The key ``/**/<node>`` applies it to the node in any namespace."""
    lines = [f"# Parameters of {node} (gcn_match_ros), every one at its default.",
             "# Generated from gcn_match_ros/ros/parameters.py; start a node with",
             "#   --ros-args --params-file config/matcher.yaml [--params-file config/<preset>.yaml]",
             "# (later files override earlier ones; a preset alone also works: what it omits stays at",
             "# the default). read-only: fixed at start-up.",
             f"/**/{node}:", "  ros__parameters:"]
    for spec in specs:
        notes = []
        if spec.low is not None:
            notes.append(f"range [{spec.low:g}, {spec.high:g}]")
        if spec.constraints:
            notes.append(spec.constraints)
        if spec.read_only:
            notes.append("read-only")
        lines.append(f"    # {spec.description}" + (f" ({'; '.join(notes)})" if notes else ""))
        lines.append(f"    {spec.name}: {_yaml_value(spec.default)}")
    return "\n".join(lines) + "\n"
