"""``method="naive"``: the classic one-step bounds (Del Prete 2018, eq. 2), the baseline that violates limits.

Only the end of the step is constrained: ``q(T) <= q_max`` (per discretisation: ``end_position_upper``),
``|v(T)| <= v_max`` and ``|a| <= a_max``. Nothing keeps the position inside during the step or the
next state viable, so these bounds let a joint run into its limit.
"""

from __future__ import annotations

from jaxlimits._src.joint_state import check_limits_type, joint_arrays
from jaxlimits._src.kinematic import common_terms, kinematic_terms
from jaxlimits._src.limit import AccelerationLimit, Terms


def naive_upper(model, d, v, v_max, a_max) -> dict:
    """Upper-side terms: acceleration, end-of-step velocity and end-of-step position (eq. 2)."""
    return {**common_terms(model, d, v, v_max, a_max), "position": model.end_position_upper(d, v)}


class Naive(AccelerationLimit):
    """The one-step bounds of eq. (2) for the discretisation ``model`` (``viable``: kernel membership)."""

    def __init__(self, limits, model, rounding_guard: bool = True):
        check_limits_type(limits)
        self.limits, self.model, self.rounding_guard = limits, model, bool(rounding_guard)

    def evaluate(self, q, v, a_prev=None) -> Terms:
        return kinematic_terms(self.model, joint_arrays(q, v, self.limits), self.rounding_guard, naive_upper)
