"""Multi-view matching methods behind one interface (:class:`Solver`); import registers them all."""
from .base import (GRAPH_PRESETS, SoftMatches, Solver, SolverConfig, available_solvers, get_solver,
                   parse_method, register)
from . import nn  # noqa: F401  (registers)
from . import spectral  # noqa: F401  (registers)
from . import matcheig  # noqa: F401  (registers)
from . import clear  # noqa: F401  (registers)
from . import matchals  # noqa: F401  (registers)
from . import pgdds  # noqa: F401  (registers)
from . import quickmatch  # noqa: F401  (registers)
from . import gcn  # noqa: F401  (registers)
from . import nn_ransac  # noqa: F401  (registers)

__all__ = ["GRAPH_PRESETS", "SoftMatches", "Solver", "SolverConfig", "available_solvers",
           "get_solver", "parse_method", "register"]
