"""The registry of limit families that ``acc_bounds``/``bound_terms`` look up by ``method=``.

A registered family is an ``AccelerationLimit`` subclass built from ``(limits, discretisation,
rounding_guard)``. Families that need the simulator's dynamics (``TorqueBox``, ``ImpactCap``) are
built directly and composed with ``jl.intersect``. ``register_method`` adds a user's family; the
contract test (``tests/test_limit_contract.py``) runs over every entry, new ones included.
"""

from __future__ import annotations

from jaxlimits._src.discretisation import make_discretisation
from jaxlimits._src.jerk import Jerk
from jaxlimits._src.jerk_paper import JerkPaper
from jaxlimits._src.limit import AccelerationLimit
from jaxlimits._src.naive import Naive
from jaxlimits._src.viability import Viability

METHODS: dict = {"naive": Naive, "viability": Viability, "jerk": Jerk, "jerk_paper": JerkPaper}


def register_method(name: str, family: type) -> None:
    """Make ``family`` available as ``acc_bounds(..., method=name)`` and ``bound_terms(..., method=name)``."""
    if not (isinstance(family, type) and issubclass(family, AccelerationLimit)):
        raise TypeError(f"register_method: family must be an AccelerationLimit subclass, got {family!r}")
    if not isinstance(name, str) or not name:
        raise ValueError(f"register_method: name must be a non-empty string, got {name!r}")
    METHODS[name] = family


def make_limit(
    method: str, limits, dt, integrator: str = "zoh", substeps: int = 1, rounding_guard: bool = True
) -> AccelerationLimit:
    """The family ``method`` for these limits and this discretisation (all checks eager)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {tuple(METHODS)}, got {method!r}")
    return METHODS[method](limits, make_discretisation(dt, integrator, substeps), rounding_guard)
