"""The discretisation a bound is exact for: ``"zoh"`` (Del Prete's zero-order hold) or ``"semi_implicit"``.

Every limit family asks its discretisation object, never its name, how a held acceleration moves a
joint: ``integrate``, ``position_gain``, ``step_peak``, ``braking_distance``, ``roundings_per_step``
and the per-side thresholds (``position_upper``, ``viability_upper``, ``end_position_upper``, and the
jerk bounds' ``ramp_roots``/``hold_roots``/``crossing_distance``). The two implementations are
``ZeroOrderHold`` (``zoh.py``) and ``SemiImplicit`` (``semi_implicit.py``).
"""

from __future__ import annotations

import numbers

import numpy as np

from jaxlimits._src.semi_implicit import SemiImplicit
from jaxlimits._src.tracing import is_traced
from jaxlimits._src.zoh import ZeroOrderHold

DISCRETISATIONS = {"zoh": ZeroOrderHold, "semi_implicit": SemiImplicit}
INTEGRATORS = tuple(DISCRETISATIONS)


def make_discretisation(dt, integrator: str = "zoh", substeps: int = 1):
    """Validate the discretisation eagerly and return its object.

    Args:
      dt: control period [s], a finite scalar > 0 (a Python float, a concrete array, or a tracer).
      integrator: ``"zoh"`` or ``"semi_implicit"`` (MuJoCo/MJX Euler and implicitfast without damping).
      substeps: physics substeps per control step, an integer >= 1; ``"zoh"`` has exactly one.

    Raises ``ValueError`` naming the field and the value.
    """
    if integrator not in DISCRETISATIONS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    if isinstance(substeps, bool) or not isinstance(substeps, numbers.Integral) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    if integrator == "zoh" and substeps != 1:
        raise ValueError(f"substeps applies to integrator='semi_implicit' only, got substeps={substeps} with 'zoh'")
    if not is_traced(dt):
        dt_arr = np.asarray(dt, dtype=np.float64)
        if dt_arr.shape != () or not np.isfinite(dt_arr) or dt_arr <= 0:
            raise ValueError(f"dt must be a finite scalar > 0, got {dt!r}")
        dt = float(dt_arr)
    if integrator == "zoh":
        return ZeroOrderHold(dt)
    return SemiImplicit(dt, int(substeps))
