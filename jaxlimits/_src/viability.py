"""``method="viability"``: Del Prete's exact viability-based bounds (2018, Alg. 3), for either discretisation.

The admissible accelerations of one joint for the next control step are ``[max(lower terms),
min(upper terms)]`` over the acceleration limit, the velocity limit (23), the position limit over
the whole step (13)-(22) and the viability of the next state (24)-(29). Each constraint is monotone
in ``a``, so the upper bound is the minimum of the upper-side thresholds and the lower bound is the
mirror image. Exact (the largest safe interval) under condition (11), checked eagerly.
"""

from __future__ import annotations

import numpy as np

from jaxlimits._src.joint_state import check_limits_type, joint_arrays
from jaxlimits._src.kinematic import common_terms, kinematic_terms
from jaxlimits._src.limit import AccelerationLimit, Terms
from jaxlimits._src.limits import JointLimits
from jaxlimits._src.tracing import is_traced

CONDITION_11_SLACK = 1e-4


def check_condition_11(limits: JointLimits, dt: float) -> None:
    """Raise if Del Prete's condition (11) fails: ``q_max - q_min >= a_max dt^2``, ``v_max >= a_max dt``.

    Under it the viability kernel of the discrete-time system equals the continuous-time one (and,
    for the semi-implicit model, the set built on the discrete braking distance), which is what
    makes the bounds exact and safe forever. Without it, full braking can overshoot zero velocity
    by more than the limits absorb and no closed form is exact; the paper's remedy is a smaller
    ``a_max``, which the message gives. The condition must hold with ``CONDITION_11_SLACK``
    (0.01 %) to spare: the rounding guard narrows the limits by a few ulps, and at exact equality
    that alone would break (11) (measured: a float32 rollout at equality left the viable set).
    Skipped when limits or ``dt`` are traced.
    """
    check_limits_type(limits)
    if not limits.concrete or is_traced(dt):
        return
    span = np.asarray(limits.q_max) - np.asarray(limits.q_min)
    a_ok = np.minimum(span / dt**2, np.asarray(limits.v_max) / dt) * (1.0 - CONDITION_11_SLACK)
    bad = np.asarray(limits.a_max) > a_ok
    if np.any(bad):
        raise ValueError(
            "condition (11) of Del Prete 2018 fails for joints "
            f"{np.flatnonzero(np.atleast_1d(bad)).tolist()}: need q_max - q_min >= a_max*dt^2 and "
            f"v_max >= a_max*dt (with {CONDITION_11_SLACK:.0e} relative slack) with dt={dt}, "
            f"got a_max={np.asarray(limits.a_max).tolist()}; use a_max <= {np.atleast_1d(a_ok).tolist()}"
        )


def viability_upper(model, d, v, v_max, a_max) -> dict:
    """Upper-side terms of Alg. 3: acceleration, velocity (23), position over the step (13)-(22), viability (24)-(29)."""
    return {
        **common_terms(model, d, v, v_max, a_max),
        "position": model.position_upper(d, v, a_max),
        "viability": model.viability_upper(d, v, a_max),
    }


class Viability(AccelerationLimit):
    """Del Prete's exact bounds (Alg. 3) for the discretisation ``model``; condition (11) checked here."""

    guarantees_safety = True

    def __init__(self, limits, model, rounding_guard: bool = True):
        check_condition_11(limits, model.period)
        self.limits, self.model, self.rounding_guard = limits, model, bool(rounding_guard)

    def evaluate(self, q, v, a_prev=None) -> Terms:
        return kinematic_terms(self.model, joint_arrays(q, v, self.limits), self.rounding_guard, viability_upper)
