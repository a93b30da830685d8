"""Tests of the layer rule of gcn_match_ros: the core never imports ROS, nothing imports benchmarks or tests."""
from __future__ import annotations

import ast
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import gcn_match_ros

PACKAGE_DIR = Path(gcn_match_ros.__file__).resolve().parent
ROS_PACKAGE = "gcn_match_ros.ros"
#: Top-level modules only the ROS layer (gcn_match_ros.ros) may import.
ROS_MODULES = ("rclpy", "gcn_match_msgs", "rcl_interfaces", "sensor_msgs", "diagnostic_msgs", "builtin_interfaces")
#: Top-level names of the repository's own scripts and tests, which the package never imports.
OUTSIDE_PACKAGE = ("benchmarks", "test", "tests", "conftest")


def _is_ros_layer(module: str) -> bool:
    return module == ROS_PACKAGE or module.startswith(ROS_PACKAGE + ".")


def core_modules() -> list:
    """Every module of gcn_match_ros outside gcn_match_ros.ros (the package itself included)."""
    found = [m.name for m in pkgutil.walk_packages(gcn_match_ros.__path__, "gcn_match_ros.")]
    return ["gcn_match_ros"] + sorted(m for m in found if not _is_ros_layer(m))


def test_importing_every_core_module_loads_no_ros():
    modules = core_modules()
    assert {"gcn_match_ros.cli", "gcn_match_ros.bags.codec", "gcn_match_ros.solvers.gcn",
            "gcn_match_ros.learn.train"} <= set(modules)
    # a fresh interpreter: this test process has imported rclpy already
    script = f"""
import importlib, json, sys
modules = {modules!r}
for name in modules:
    importlib.import_module(name)
loaded = sorted(m for m in sys.modules if m.startswith(("rclpy", "gcn_match_msgs")))
import gcn_match_ros.ros.parameters  # the check can see rclpy: the ROS layer loads it
print(json.dumps({{"ros_after_core": loaded, "ros_layer_loads_rclpy": "rclpy" in sys.modules,
                  "missing": [m for m in modules if m not in sys.modules]}}))
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["missing"] == []
    assert report["ros_after_core"] == [], report["ros_after_core"]
    assert report["ros_layer_loads_rclpy"]


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str, is_package: bool = False) -> set:
    """Absolute names of everything ``source`` (module ``module``) imports: relative imports
    resolved, for ``from a import b`` both ``a`` and ``a.b``, and literal names given to
    importlib.import_module or __import__."""
    package = module if is_package else module.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                base = ".".join(base + ([node.module] if node.module else []))
            else:
                base = node.module
            out.add(base)
            out.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant) \
                and isinstance(node.args[0].value, str):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            if name in ("import_module", "__import__"):
                out.add(node.args[0].value)
    return out


def imports_of(path: Path) -> set:
    """:func:`imported_modules` of a file of the package."""
    return imported_modules(path.read_text(), _module_name(path), path.name == "__init__.py")


def _package_files():
    return sorted(PACKAGE_DIR.rglob("*.py"))


def test_import_collector_resolves_every_form_of_import():
    """The static checks below see what a module imports, relative imports included."""
    source = """
import rclpy.node
from sensor_msgs.msg import Image
from ..ros import conversions
from .. import ros
from . import codec
from .typesys import typestore
import importlib
importlib.import_module("gcn_match_msgs.msg")
"""
    assert imported_modules(source, "gcn_match_ros.bags.example") == {
        "rclpy.node", "sensor_msgs.msg", "sensor_msgs.msg.Image", "gcn_match_ros.ros",
        "gcn_match_ros.ros.conversions", "gcn_match_ros", "gcn_match_ros.bags", "gcn_match_ros.bags.codec",
        "gcn_match_ros.bags.typesys", "gcn_match_ros.bags.typesys.typestore", "importlib", "gcn_match_msgs.msg"}
    # in a package's __init__, "." is the package itself
    assert imported_modules("from . import nn", "gcn_match_ros.solvers", is_package=True) == {
        "gcn_match_ros.solvers", "gcn_match_ros.solvers.nn"}
    # and on the real ROS layer it finds rclpy: the checks are not vacuous
    ros_files = [p for p in _package_files() if _is_ros_layer(_module_name(p))]
    assert any("rclpy" in {n.split(".")[0] for n in imports_of(p)} for p in ros_files)


def test_core_files_import_nothing_from_ros():
    checked, offences = 0, []
    for path in _package_files():
        if _is_ros_layer(_module_name(path)):
            continue
        checked += 1
        for name in sorted(imports_of(path)):
            if name.split(".")[0] in ROS_MODULES or _is_ros_layer(name):
                offences.append(f"{path.relative_to(PACKAGE_DIR.parent)}: {name}")
    assert checked > 50  # every core file, not none
    assert offences == []


def test_package_imports_nothing_from_benchmarks_or_tests():
    offences = [f"{path.relative_to(PACKAGE_DIR.parent)}: {name}" for path in _package_files()
                for name in sorted(imports_of(path)) if name.split(".")[0] in OUTSIDE_PACKAGE]
    assert offences == []
