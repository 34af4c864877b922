"""Joint acceleration bounds: the one-step ``naive`` bounds and the exact ``viability`` bounds.

Del Prete 2018, Alg. 3: the admissible accelerations of one joint for the next control step are
``[max(lower bounds), min(upper bounds)]`` over the acceleration limit, the velocity limit (23),
the position limit over the step (13)-(22) and the viability of the next state (24)-(29).
Each of these constraints is monotone in ``a``, so the upper bound is the minimum of the upper-side
thresholds and the lower bound is the mirror image of the upper one (``q -> -q``, ``v -> -v``).
The model of the step is ``integrator="zoh"`` (the paper's) or ``"semi_implicit"`` (MuJoCo/MJX
with ``substeps`` physics steps per control step); see ``zoh.py`` and ``semi_implicit.py``.
"""

from __future__ import annotations

import numbers
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits._src.limits import JointLimits
from jaxlimits._src.semi_implicit import SemiImplicit
from jaxlimits._src.zoh import ZeroOrderHold

METHODS = ("naive", "viability", "jerk", "jerk_paper")
JERK_METHODS = ("jerk", "jerk_paper")
INTEGRATORS = ("zoh", "semi_implicit")
CONDITION_11_SLACK = 1e-4


class Bounds(NamedTuple):
    """Admissible joint accelerations for the next control step.

    lower, upper: ``(..., n)`` [rad/s^2], ``lower <= upper`` always.
    viable: ``(..., n)`` bool, whether the current state lies in the viability kernel of the model.
      Where it is False the interval is the best-effort braking action (see ``acc_bounds``).
    """

    lower: jax.Array
    upper: jax.Array
    viable: jax.Array


def make_model(dt, integrator: str, substeps: int):
    """Validate the discretisation (eagerly) and return its model object."""
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    if isinstance(substeps, bool) or not isinstance(substeps, numbers.Integral) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    if integrator == "zoh" and substeps != 1:
        raise ValueError(f"substeps applies to integrator='semi_implicit' only, got substeps={substeps} with 'zoh'")
    if not isinstance(dt, jax.core.Tracer):
        dt_arr = np.asarray(dt, dtype=np.float64)
        if dt_arr.shape != () or not np.isfinite(dt_arr) or dt_arr <= 0:
            raise ValueError(f"dt must be a finite scalar > 0, got {dt!r}")
        dt = float(dt_arr)
    return ZeroOrderHold(dt) if integrator == "zoh" else SemiImplicit(dt, int(substeps))


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
    if not limits.concrete or isinstance(dt, jax.core.Tracer):
        return
    span = np.asarray(limits.q_max) - np.asarray(limits.q_min)
    a_ok = np.minimum(span / dt**2, np.asarray(limits.v_max) / dt) * (1.0 - CONDITION_11_SLACK)
    bad = np.asarray(limits.a_max) > a_ok
    if np.any(bad):
        raise ValueError(
            "condition (11) of Del Prete 2018 fails for joints "
            f"{np.flatnonzero(np.atleast_1d(bad)).tolist()}: need q_max - q_min >= a_max*dt^2 and "
            f"v_max >= a_max*dt (with {CONDITION_11_SLACK:.0e} relative slack) with dt={dt}, got a_max={np.asarray(limits.a_max).tolist()}; "
            f"use a_max <= {np.atleast_1d(a_ok).tolist()}"
        )


def _check_limits_type(limits) -> None:
    if not isinstance(limits, JointLimits):
        raise TypeError(f"limits must be a JointLimits, got {type(limits).__name__}")


def _state_and_limits(q, v, limits: JointLimits):
    """Broadcast the state and the limits (cast to the state's float dtype) to one shape."""
    _check_limits_type(limits)
    q, v = jnp.asarray(q), jnp.asarray(v)
    dtype = jnp.promote_types(jnp.result_type(q, v), jnp.float32)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(f"q and v must be real, got dtype {dtype}")
    try:
        shape = jnp.broadcast_shapes(q.shape, v.shape)
    except ValueError as exc:
        raise ValueError(f"q shape {q.shape} and v shape {v.shape} do not broadcast") from exc
    lim_shape = jnp.shape(limits.q_min)
    if lim_shape and (not shape or shape[-1] != lim_shape[0]):
        raise ValueError(f"state shape {shape} does not end in the {lim_shape[0]} joints of the limits")
    fields = [jnp.broadcast_to(jnp.asarray(f, dtype), shape) for f in (limits.q_min, limits.q_max, limits.v_max, limits.a_max)]
    return jnp.broadcast_to(q.astype(dtype), shape), jnp.broadcast_to(v.astype(dtype), shape), *fields


def _rounding_guard(q_min, q_max, v_max, a_max, substeps: int, stop_steps=0.0):
    """Limits tightened by the roundoff of a whole stop, so rounding cannot carry a state out.

    The bounds are exact in real arithmetic; a state riding one is then advanced in floating point.
    Each rounded update moves the position by up to half an ulp of ``|q|`` (a zero-order-hold step
    rounds ~3 times; a semi-implicit one rounds ``q`` once per substep), and a few ulps of relative
    error in the velocity move a state on the viability curve by ``~ eps v_max^2 / a_max`` in
    position (the braking distance ``v^2 / (2 a_max)`` has relative slope 2).

    One step's worth is not enough: on the viability curve the bound *is* full braking, nothing
    corrects the state until it stops, and the roundings of every update of the stop add up (they
    need not cancel: float32 rollouts with ``v_max / a_max = 0.8 s`` went 2.4 um past the limit with
    one step's margin). So the margin covers ``R = 2 + substeps (1 + stop_steps)`` roundings, where
    ``stop_steps = ceil(v_max / (a_max dt))`` bounds the control steps of a stop from ``v_max``:
    the position limits move in by ``R eps (max|q_lim| + 2 v_max^2 / a_max)`` and ``v_max`` by
    ``R eps v_max``. Float32, q_max = 2, v_max = 2, a_max = 12, dt = 0.01 s, 5 substeps: 18 steps,
    R = 97, 37 um of range; float64: ~1e-13, nothing measurable. (``stop_steps=0`` is the one-step
    margin, still used by the jerk-aware bounds.)
    """
    eps = jnp.finfo(q_min.dtype).eps * (2.0 + substeps * (1.0 + stop_steps))
    m_q = eps * (jnp.maximum(jnp.abs(q_min), jnp.abs(q_max)) + 2.0 * v_max * v_max / a_max)
    return q_min + m_q, q_max - m_q, v_max * (1.0 - eps)


def _saturate(q, v, q_min, q_max, v_max, a_max, period):
    """Clip far-out states so that no formula overflows; inside ±(range, 2 v_max + 4 a_max T) it is the identity.

    Beyond those the answer is already full braking; the clip keeps it finite (values and grads).
    """
    span = q_max - q_min
    v_sat = 2.0 * v_max + 4.0 * a_max * period
    return jnp.clip(q, q_min - span, q_max + span), jnp.clip(v, -v_sat, v_sat)


def _upper_terms(model, method, d, v, v_max, a_max) -> dict:
    """The upper-side thresholds of Alg. 3, one per constraint family, before taking their minimum."""
    terms = {"acceleration": jnp.broadcast_to(a_max, d.shape), "velocity": (v_max - v) / model.period}
    if method == "naive":
        terms["position"] = model.end_position_upper(d, v)
    else:
        terms["position"] = model.position_upper(d, v, a_max)
        terms["viability"] = model.viability_upper(d, v, a_max)
    return terms


def _upper_side(model, method, d, v, v_max, a_max):
    """Largest admissible acceleration on the upper side, before clipping to ``[-a_max, a_max]``."""
    terms = list(_upper_terms(model, method, d, v, v_max, a_max).values())
    out = terms[0]
    for t in terms[1:]:
        out = jnp.minimum(out, t)
    return out


def _viable(model, q, v, q_min, q_max, v_max, a_max):
    """Membership of the viability kernel of ``model`` (eq. 10; discrete braking for semi-implicit)."""
    inside = (q >= q_min) & (q <= q_max) & (jnp.abs(v) <= v_max)
    up = model.braking_distance(v, a_max) <= q_max - q
    down = model.braking_distance(-v, a_max) <= q - q_min
    return inside & up & down


def acc_bounds(
    q,
    v,
    limits: JointLimits,
    dt,
    method: str = "viability",
    integrator: str = "zoh",
    substeps: int = 1,
    rounding_guard: bool = True,
    a_prev=None,
) -> Bounds:
    """Bounds on the joint accelerations of the next control step.

    Args:
      q, v: joint positions [rad] and velocities [rad/s], shape ``(..., n)`` (broadcast together);
        any float dtype, float32 or float64 (the result has the state's dtype).
      limits: ``JointLimits`` with fields of shape ``()`` or ``(n,)``.
      dt: control period [s], a Python float (or a concrete scalar).
      method: ``"viability"`` — Del Prete's exact bounds (Alg. 3): every ``a`` in the interval keeps
          the position inside its limits during the whole step, the velocity and acceleration
          inside theirs, and the next state viable, so it holds forever by induction; and no ``a``
          outside it does. Requires condition (11) (checked eagerly, ``ValueError`` otherwise).
        ``"naive"`` — the classic one-step bounds (eq. 2): end-of-step position and velocity only;
          the baseline that violates limits.
      integrator: ``"zoh"`` (acceleration held, continuous-time positions; the paper) or
        ``"semi_implicit"`` (MuJoCo/MJX Euler/implicitfast; positions at every substep).
      substeps: physics substeps per control step for ``"semi_implicit"``.
      rounding_guard: tighten the limits by ``2 + substeps`` ulps of their magnitude so that the
        rounding of the next-state update cannot carry a state riding a bound outside (needed in
        float32; see ``_rounding_guard``). ``False`` gives the exact real-arithmetic bound.
      a_prev: the previous step's joint accelerations [rad/s^2], broadcast with ``q``; required by
        (and only allowed for) ``method="jerk"`` — the exact jerk-aware bounds for the state
        ``(q, v, a_prev)`` with ``|a - a_prev| <= j_max dt`` (``jerk.py``, needs ``limits.j_max``)
        — and ``method="jerk_paper"`` — Meguenani et al.'s eqs. (39)-(40) (``jerk_paper.py``).

    Returns:
      ``Bounds(lower, upper, viable)``, each ``(..., n)``; ``-a_max <= lower <= upper <= a_max``.

    Non-viable states (past a limit, too fast to stop, or rounded just outside) are not an error:
    ``viable`` is False and the interval is the best effort. Constraints that can still be met are
    met (e.g. a state at rest just past ``q_max`` gets accelerations that bring it back inside by
    the end of the step); when the upper- and lower-side constraints conflict, the interval collapses
    to the single braking action on the side the joint is moving toward (at rest: the side of the
    range's midpoint it is on), which is ``-a_max``/``+a_max`` unless less suffices.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method in JERK_METHODS:
        _check_limits_type(limits)
        if a_prev is None:
            raise ValueError(f"method={method!r} needs a_prev (the previous joint accelerations)")
        if limits.j_max is None:
            raise ValueError(f"method={method!r} needs a jerk limit: JointLimits(..., j_max=...) got j_max=None")
        if method == "jerk":
            from jaxlimits._src.jerk import jerk_acc_bounds as impl
        else:
            from jaxlimits._src.jerk_paper import paper_acc_bounds as impl
        return impl(q, v, a_prev, limits, dt, integrator, substeps, rounding_guard)
    if a_prev is not None:
        raise ValueError(f"a_prev is only used by the jerk methods {JERK_METHODS}, not method={method!r}")
    model = make_model(dt, integrator, substeps)
    _check_limits_type(limits)
    if method == "viability":
        check_condition_11(limits, model.period)
    q, v, q_min, q_max, v_max, a_max = _state_and_limits(q, v, limits)
    viable = _viable(model, q, v, q_min, q_max, v_max, a_max)
    if rounding_guard:
        stop_steps = jnp.ceil(v_max / (a_max * model.period))
        q_min, q_max, v_max = _rounding_guard(q_min, q_max, v_max, a_max, getattr(model, "n", 3), stop_steps)
    q, v = _saturate(q, v, q_min, q_max, v_max, a_max, model.period)
    upper = jnp.clip(_upper_side(model, method, q_max - q, v, v_max, a_max), -a_max, a_max)
    lower = jnp.clip(-_upper_side(model, method, q - q_min, -v, v_max, a_max), -a_max, a_max)
    conflict = lower > upper
    toward_upper = (v > 0) | ((v == 0) & (2.0 * q >= q_min + q_max))
    brake = jnp.where(toward_upper, upper, lower)
    return Bounds(jnp.where(conflict, brake, lower), jnp.where(conflict, brake, upper), viable)


def is_viable(q, v, limits: JointLimits, integrator: str = "zoh", dt=None, substeps: int = 1):
    """Whether ``(q, v)`` is in the viability kernel: some future keeps every limit forever.

    ``integrator="zoh"``: eq. (10), ``q_min <= q <= q_max``, ``|v| <= v_max`` and
    ``-sqrt(2 a_max (q - q_min)) <= v <= sqrt(2 a_max (q_max - q))`` (needs no ``dt``).
    ``"semi_implicit"``: the same with the discrete braking distance of substep ``dt / substeps``
    in place of ``v^2 / (2 a_max)`` (needs ``dt``). Returns a bool array of the broadcast shape.
    """
    if integrator == "semi_implicit" and dt is None:
        raise ValueError("is_viable(integrator='semi_implicit') needs dt (and substeps)")
    model = make_model(1.0 if dt is None else dt, integrator, substeps)
    return _viable(model, *_state_and_limits(q, v, limits))


def bound_terms(q, v, limits: JointLimits, dt, method: str = "viability", integrator: str = "zoh", substeps: int = 1):
    """Each constraint's own bound, to see which one is active (Del Prete 2018, Fig. 3).

    Returns ``{"upper": {...}, "lower": {...}}``, each mapping ``"acceleration"``, ``"velocity"``,
    ``"position"`` and (for ``viability``) ``"viability"`` to an array of the broadcast shape
    [rad/s^2]. ``acc_bounds`` is their min/max, clipped and resolved; no rounding guard here.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    model = make_model(dt, integrator, substeps)
    q, v, q_min, q_max, v_max, a_max = _state_and_limits(q, v, limits)
    upper = _upper_terms(model, method, q_max - q, v, v_max, a_max)
    lower = {k: -t for k, t in _upper_terms(model, method, q - q_min, -v, v_max, a_max).items()}
    return {"upper": upper, "lower": lower}
