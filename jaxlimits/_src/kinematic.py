"""What the position/velocity/acceleration families (``naive``, ``viability``) share: the viability
kernel of a discretisation (Del Prete 2018, eq. 10) and the guarded, saturated evaluation of one
side's thresholds with the lower side as the mirror image of the upper one (``q -> -q``, ``v -> -v``)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits._src.joint_state import JointArrays, guard_limits, inside_limits, saturate
from jaxlimits._src.limit import Terms, toward_upper_side


def in_kernel(model, a: JointArrays):
    """Membership of the viability kernel of ``model`` (eq. 10; the discrete braking distance for semi-implicit)."""
    up = model.braking_distance(a.v, a.a_max) <= a.q_max - a.q
    down = model.braking_distance(-a.v, a.a_max) <= a.q - a.q_min
    return inside_limits(a) & up & down


def kinematic_terms(model, a: JointArrays, rounding_guard: bool, upper_side) -> Terms:
    """``Terms`` of a family whose upper side is ``upper_side(model, d, v, v_max, a_max) -> {name: (..., n)}``.

    ``d = q_max - q`` is the distance to the upper limit. The limits are tightened by ``guard_limits``
    (``rounding_guard``; ``stop_steps = ceil(v_max / (a_max T))``) and far-out states saturated first.
    """
    viable = in_kernel(model, a)
    q_min, q_max, v_max, a_max = a.q_min, a.q_max, a.v_max, a.a_max
    if rounding_guard:
        # a viable state is no faster than its braking distance allows within the range (zoh: sqrt(2 a_max span);
        # semi-implicit: D(v) >= v^2 / (2 a_max) - v h / 2, within a_max h of it): the stop the guard covers
        v_reach = jnp.minimum(v_max, jnp.sqrt(2.0 * a_max * (q_max - q_min)) + a_max * model.period)
        stop_steps = jnp.ceil(v_reach / (a_max * model.period))
        q_min, q_max, v_max = guard_limits(q_min, q_max, v_max, a_max, model.roundings_per_step, stop_steps, v_reach)
    q, v = saturate(a.q, a.v, q_min, q_max, v_max, a_max, model.period)
    upper = upper_side(model, q_max - q, v, v_max, a_max)
    lower = {k: -t for k, t in upper_side(model, q - q_min, -v, v_max, a_max).items()}
    return Terms(upper, lower, viable, toward_upper_side(q, v, q_min, q_max))


def common_terms(model, d, v, v_max, a_max) -> dict:
    """The acceleration limit and the velocity limit at the end of the step (eq. 23), upper side."""
    return {"acceleration": jnp.broadcast_to(a_max, d.shape), "velocity": (v_max - v) / model.period}
