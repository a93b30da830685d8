"""Multi-view matching methods behind one interface (:class:`Solver`), made by name with
:func:`create`; importing this package registers them all."""
from .base import SoftMatches, Solver, SolverConfig
from .registry import available_solvers, create, parse_method, parse_method_list, register, settings_of
from . import nn  # noqa: F401,E402  (registers)
from . import spectral  # noqa: F401,E402  (registers)
from . import matcheig  # noqa: F401,E402  (registers)
from . import clear  # noqa: F401,E402  (registers)
from . import matchals  # noqa: F401,E402  (registers)
from . import pgdds  # noqa: F401,E402  (registers)
from . import quickmatch  # noqa: F401,E402  (registers)
from . import gcn  # noqa: F401,E402  (registers)
from . import nn_ransac  # noqa: F401,E402  (registers)

__all__ = ["SoftMatches", "Solver", "SolverConfig", "available_solvers", "create", "parse_method",
           "parse_method_list", "register", "settings_of"]
