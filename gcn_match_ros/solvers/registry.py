"""Solvers by name: ``create("matchals:iters=50")``, what exists, and what each takes."""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any, Dict, List, Tuple, Type

from .base import Solver

__all__ = ["register", "create", "available_solvers", "settings_of", "parse_method", "parse_method_list"]

_REGISTRY: Dict[str, Type[Solver]] = {}


def register(cls: Type[Solver]) -> Type[Solver]:
    """Class decorator adding a solver to the registry under ``cls.name``."""
    if cls.name in _REGISTRY:
        raise ValueError(f"solver '{cls.name}' registered twice")
    _REGISTRY[cls.name] = cls
    return cls


def available_solvers() -> List[str]:
    """Names of the registered solvers, sorted."""
    return sorted(_REGISTRY)


def parse_method(spec: str) -> Tuple[str, Dict[str, str]]:
    """``"matchals:iters=50,graph=mutual"`` -> ("matchals", {"iters": "50", "graph": "mutual"}).

    Raises:
        ValueError: a setting that is not ``key=value``.
    """
    name, _, rest = spec.partition(":")
    settings = {}
    for item in filter(None, rest.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key:
            raise ValueError(f"method '{spec}': setting '{item}' is not key=value")
        settings[key.strip()] = value.strip()
    return name.strip(), settings


def parse_method_list(text: str) -> List[str]:
    """Several solver specs in one argument: separated by ';', or by ',' when there is no ';'
    (a spec with more than one setting has commas of its own: ``"gcn:verify=false,threshold=0.3;nn"``).
    Empty items are dropped."""
    return [m for m in text.split(";" if ";" in text else ",") if m]


def _solver_class(name: str) -> Type[Solver]:
    """The registered class of ``name``, importing ``gcn_match_ros.solvers.<name>`` first when it is
    not registered yet (a solver module of the package that nothing imported)."""
    if name not in _REGISTRY and name.isidentifier():
        try:
            importlib.import_module(f"{__package__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__package__}.{name}":
                raise  # the solver module exists but a dependency of it is missing
    if name not in _REGISTRY:
        raise ValueError(f"unknown method '{name}'; available: {', '.join(available_solvers())}")
    return _REGISTRY[name]


def settings_of(name: str) -> Tuple[str, ...]:
    """The settings solver ``name`` takes (its configuration's fields).

    Raises:
        ValueError: unknown solver.
    """
    return tuple(f.name for f in dataclasses.fields(_solver_class(name).Config))


def create(spec: str, **overrides: Any) -> Solver:
    """A solver from ``name`` or ``name:key=value,...``, with ``overrides`` (settings given as
    values, e.g. from ROS parameters) added; string values are read as the setting's type.

    Raises:
        ValueError: unknown solver or setting, a value that does not read, a setting given in
            ``spec`` and in ``overrides`` with different values, or a solver that cannot be made
            (e.g. a missing or corrupt checkpoint).
    """
    name, settings = parse_method(spec)
    cls = _solver_class(name)
    for key, value in overrides.items():
        if key in settings and str(settings[key]) != str(value):
            raise ValueError(f"setting '{key}' given twice: '{settings[key]}' in '{spec}' and '{value}'")
        settings[key] = value
    return cls(**settings)
