"""The inputs every joint-limit family shares: the state and limits broadcast to one shape and dtype,
the rounding guard, and the saturation of far-out states."""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from jaxlimits._src.limits import JointLimits


class JointArrays(NamedTuple):
    """State and limits broadcast to one shape ``(..., n)`` and the state's float dtype (at least float32).

    q, v, a_prev: positions [rad], velocities [rad/s], previous accelerations [rad/s^2] (``None`` when
    not given). q_min, q_max, v_max, a_max, j_max: the limits (``j_max`` is ``None`` without a jerk limit).
    """

    q: jax.Array
    v: jax.Array
    a_prev: Optional[jax.Array]
    q_min: jax.Array
    q_max: jax.Array
    v_max: jax.Array
    a_max: jax.Array
    j_max: Optional[jax.Array]


def check_limits_type(limits) -> None:
    if not isinstance(limits, JointLimits):
        raise TypeError(f"limits must be a JointLimits, got {type(limits).__name__}")


def joint_arrays(q, v, limits: JointLimits, a_prev=None) -> JointArrays:
    """Broadcast ``q``, ``v`` (and ``a_prev``) and the limits to one shape and dtype; eager shape/type errors."""
    check_limits_type(limits)
    state = {"q": jnp.asarray(q), "v": jnp.asarray(v)}
    if a_prev is not None:
        state["a_prev"] = jnp.asarray(a_prev)
    dtype = jnp.promote_types(jnp.result_type(*state.values()), jnp.float32)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"q and v must be real, got dtype {dtype}")
    try:
        shape = jnp.broadcast_shapes(*(x.shape for x in state.values()))
    except ValueError as exc:
        shapes = ", ".join(f"{k} shape {x.shape}" for k, x in state.items())
        raise ValueError(f"{shapes} do not broadcast") from exc
    lim_shape = jnp.shape(limits.q_min)
    if lim_shape and (not shape or shape[-1] != lim_shape[0]):
        raise ValueError(f"state shape {shape} does not end in the {lim_shape[0]} joints of the limits")

    def cast(x):
        return None if x is None else jnp.broadcast_to(jnp.asarray(x).astype(dtype), shape)

    return JointArrays(
        cast(state["q"]),
        cast(state["v"]),
        cast(state.get("a_prev")),
        cast(limits.q_min),
        cast(limits.q_max),
        cast(limits.v_max),
        cast(limits.a_max),
        cast(limits.j_max),
    )


def guard_limits(q_min, q_max, v_max, a_max, roundings, stop_steps, v_reach=None):
    """Limits tightened by the roundoff of a whole stop, so rounding cannot carry a state out.

    The bounds are exact in real arithmetic; a state riding one is then advanced in floating point.
    Each rounded update moves the position by up to half an ulp of ``|q|`` (``roundings`` per control
    step: ``discretisation.roundings_per_step``, 3 for the zero-order hold, one per substep for the
    semi-implicit model), and a few ulps of relative error in the velocity move a state on the
    viability curve by ``~ eps v_max^2 / a_max`` in position (the braking distance has relative slope 2).

    One step's worth is not enough: on the viability curve the bound *is* full braking, nothing
    corrects the state until it stops, and the roundings of every update of the stop add up (float32
    rollouts with ``v_max / a_max = 0.8 s`` went 2.4 um past the limit with one step's margin). So the
    margin covers ``R = 2 + roundings (1 + stop_steps)`` roundings, ``stop_steps`` bounding the control
    steps of a stop (``ceil(v_max / (a_max dt))`` for the viability bounds): the position limits move
    in by ``R eps (max|q_lim| + 2 v_max^2 / a_max)`` and ``v_max`` by ``R eps v_max``, with ``eps`` the
    machine epsilon of the limits' dtype. Float32, q_max = 2, v_max = 2, a_max = 12, dt = 0.01 s,
    5 substeps: 17 steps, R = 92, 29 um per limit (58 um of range); float64: ~1e-13, nothing measurable.

    ``v_reach`` (default ``v_max``): the fastest speed a viable state can have, where the range caps it
    below ``v_max`` (``kinematic_terms``: ``sqrt(2 a_max (q_max - q_min)) + a_max T``); the callers size
    ``stop_steps`` with it too. Without it a short range with a long stop at ``v_max`` (float32, range 1,
    v_max 1, a_max 1e-3, dt 1 s: ``2 v_max^2 / a_max = 2000``) got a margin larger than half the range:
    the guarded limits crossed and a joint at rest on ``q_max`` was given ``+a_max`` (found by fuzzing).
    """
    eps = jnp.finfo(q_min.dtype).eps * (2.0 + roundings * (1.0 + stop_steps))
    v_q = v_max if v_reach is None else v_reach
    m_q = eps * (jnp.maximum(jnp.abs(q_min), jnp.abs(q_max)) + 2.0 * v_q * v_q / a_max)
    # a range too short for the dtype at its magnitude (float32, [1000, 1000.01]: eps |q| alone exceeds half of
    # it): the guarded limits meet at the midpoint instead of crossing, every state there brakes toward it
    m_q = jnp.minimum(m_q, 0.5 * (q_max - q_min))
    return q_min + m_q, q_max - m_q, v_max * (1.0 - eps)


def saturate(q, v, q_min, q_max, v_max, a_max, period):
    """Clip far-out states so that no formula overflows; inside ±(range, 2 v_max + 4 a_max T) it is the identity.

    Beyond those the answer is already full braking; the clip keeps it finite (values and grads).
    """
    span = q_max - q_min
    v_sat = 2.0 * v_max + 4.0 * a_max * period
    return jnp.clip(q, q_min - span, q_max + span), jnp.clip(v, -v_sat, v_sat)


def inside_limits(a: JointArrays):
    """Position, velocity (and, with ``a_prev``, acceleration) inside their limits, per joint."""
    inside = (a.q >= a.q_min) & (a.q <= a.q_max) & (jnp.abs(a.v) <= a.v_max)
    if a.a_prev is not None:
        inside = inside & (jnp.abs(a.a_prev) <= a.a_max)
    return inside
