"""gcn_match_ros: cycle-consistent multi-camera keypoint matching with a graph neural network (ROS 2).

The small public face::

    from gcn_match_ros import create_solver, load_problem
    result = create_solver("gcn").solve(load_problem("window.npz"))   # tracks + soft pair scores

- :class:`Problem`, :class:`Result` and their ``.npz`` files (:mod:`.problem`);
- :class:`Frame`, :class:`WindowConfig`, :class:`WindowAssembler`: camera frames into windows (:mod:`.windowing`);
- :func:`create_solver`, :func:`available_solvers`: every matching method by name (:mod:`.solvers`);
- :func:`load_checkpoint`: a trained model (:mod:`.learn.checkpoint`).

The core never imports ROS; the ROS nodes are in :mod:`gcn_match_ros.ros`. Names load on first
use, so importing one module (e.g. a bag tool's) does not import torch.
"""
from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_FACE = {
    "Problem": ("problem", "Problem"), "Result": ("problem", "Result"),
    "load_problem": ("problem", "load_problem"), "save_problem": ("problem", "save_problem"),
    "load_result": ("problem", "load_result"), "save_result": ("problem", "save_result"),
    "Frame": ("windowing", "Frame"), "WindowConfig": ("windowing", "WindowConfig"),
    "WindowAssembler": ("windowing", "WindowAssembler"),
    "create_solver": ("solvers", "create"), "available_solvers": ("solvers", "available_solvers"),
    "load_checkpoint": ("learn.checkpoint", "load_checkpoint"),
}

__all__ = ["__version__", *_FACE]


def __getattr__(name: str) -> Any:
    if name not in _FACE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attr = _FACE[name]
    value = getattr(importlib.import_module(f"{__name__}.{module}"), attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(list(globals()) + list(_FACE))
