"""Jerk-aware acceleration bounds: the state is ``(q, v, a_prev)`` and ``|a_k - a_{k-1}| <= j_max dt``.

Derivation (``docs/jerk.md`` has the long form). Work on the upper side with ``d = q_max - q``;
the lower side is the mirror (``d = q - q_min``, ``v -> -v``, ``a_prev -> -a_prev``, negated).
Write ``A = a_max``, ``delta = j_max T`` (the largest change of acceleration per control step).

* **Max braking is pointwise lowest.** If the command of this step is ``a_0 = a``, every admissible
  future has ``a_i >= max(a - i delta, -A)`` (induction on the jerk limit), hence velocities and
  positions (at every instant for zoh, every substep for the semi-implicit model) at least those of
  the *max-braking* plan ``B(a)``: ``a_i = max(a - i delta, -A)``. So ``peak_B(a) <= d`` and
  ``vpeak_B(a) <= v_max`` are *necessary* for ``a`` to be admissible.
* **And sufficient** (given enough room, ``check_jerk_condition``): ``B(a)`` reaches its peak
  where its velocity crosses zero; from there the recovery plan (ramp the acceleration back to 0 at
  full jerk, then a triangular jerk-limited stop of the backward motion) reaches rest
  (``v = 0, a = 0``) travelling back at most ``back_travel`` and at speeds at most ``back_speed``,
  both computed from the limits. When the range is at least twice that travel (plus margins), the
  upper-side and lower-side conditions can be checked separately, exactly as Del Prete's condition
  (11) decouples them without jerk; the long-horizon LP in the tests (which couples everything)
  confirms it. So the exact upper bound is the largest ``a`` in the jerk/acceleration box with
  ``vpeak_B(a) <= v_max`` and ``peak_B(a) <= d``.
* **Velocity threshold, closed form.** ``vpeak_B(a) - v = T sum_i max(a - i delta, 0) =
  T max_{K >= 1} (K a - delta K (K - 1) / 2)``, so the threshold is
  ``min_{K >= 1} (R + delta K (K - 1) / 2) / K`` with ``R = (v_max - v) / T``; the minimising
  integer is next to ``sqrt(2 R / delta)`` (the paper's eqs. 13-14 happen to be exact here).
* **Position threshold, fixed bisection.** ``peak_B(a)`` is nondecreasing in ``a`` (pointwise
  larger accelerations) and has a closed form: in the ramp phase (``i < m``,
  ``m = ceil((a + A) / delta)``) the step-boundary states are

      v_i = v + T (i a - delta i (i - 1) / 2),
      p_i = T i v + T^2 (a i (i - 1) / 2 - delta i (i - 1) (i - 2) / 6) + c (i a - delta i (i - 1) / 2),

  with ``c = T^2 / 2`` (zoh) or ``h^2 n (n + 1) / 2`` (semi-implicit, ``h = T / n``); the step in
  which the velocity crosses zero is next to the larger root of the quadratic ``v_x = 0``; three
  candidate steps are evaluated exactly (continuous-time interior maximum for zoh, the best
  substeps for the semi-implicit model). In the hold phase (``a = -A`` from step ``m`` on) the
  peak is ``p_m + v_m^2 / (2 A)`` (zoh) or ``p_m + D(v_m)`` (the semi-implicit discrete braking
  distance of ``semi_implicit.py``). Every value taken is a real position of ``B(a)``, so the max
  over candidates is the peak as soon as the crossing step is among them. The threshold is found
  by ``BISECTION_STEPS`` halvings of the box ``[max(a_prev - delta, -A), min(a_prev + delta, A,
  v-threshold)]`` (at most ``2 delta`` wide), always returning the end *known* to pass: safe by
  construction, below the exact bound by at most ``2 delta / 2^BISECTION_STEPS``. Its gradient
  is the implicit-function one (``-dP/dtheta / dP/da`` at the root).
"""

from __future__ import annotations

import functools

import numpy as np

import jax
import jax.numpy as jnp

from jaxlimits._src.bounds import Bounds, _check_limits_type, _rounding_guard, make_model
from jaxlimits._src.limits import JointLimits
from jaxlimits._src.safe_math import tiny_floor

BISECTION_STEPS = 22
JERK_CONDITION_SLACK = 1e-3


# ----------------------------------------------------------------------------- the braking plan


def _step_coeff(model):
    """``c`` in ``p_{i+1} = p_i + T v_i + c a_i`` (position gained per step by a held ``a``)."""
    if model.name == "zoh":
        return 0.5 * model.dt * model.dt
    return model.h * model.h * model.n * (model.n + 1) / 2.0


def _ramp_state(i, v, a, T, delta, c):
    """Displacement and velocity at the start of step ``i`` of the ramp ``a_j = a - j delta``."""
    tri = i * (i - 1.0) / 2.0
    p = T * i * v + T * T * (a * tri - delta * tri * (i - 2.0) / 3.0) + c * (i * a - delta * tri)
    return p, v + T * (i * a - delta * tri)


def _step_max(model, p, v, a):
    """Largest displacement reached during one step with held ``a`` from ``(p, v)`` (after its start)."""
    if model.name == "zoh":
        T = model.dt
        end = p + T * v + 0.5 * T * T * a
        inside = (v > 0) & (a < 0) & (v < -a * T)
        a_safe = jnp.where(inside, a, -1.0)
        return jnp.where(inside, p - v * v / (2.0 * a_safe), end)
    h, n = model.h, model.n
    neg = a < 0
    a_safe = jnp.where(neg, a, -1.0)
    k_star = jnp.where(neg, -jax.lax.stop_gradient(v / a_safe) / h - 0.5, float(n))
    k0 = jnp.floor(jnp.clip(k_star, 1.0, float(n)))
    best = None
    for k in (k0, jnp.minimum(k0 + 1.0, float(n)), jnp.full_like(k0, float(n))):
        pk = p + k * h * v + h * h * a * k * (k + 1.0) / 2.0
        best = pk if best is None else jnp.maximum(best, pk)
    return best


def _hold_peak(model, p, v, a_max):
    """Peak displacement from ``(p, v)`` under ``a = -a_max`` held forever (the hold phase)."""
    if model.name == "zoh":
        vp = jnp.maximum(v, 0.0)
        return p + vp * vp / (2.0 * a_max)
    return p + model.braking_distance(v, a_max)


def braking_peak(model, v, a, a_max, delta):
    """``peak_B(a)``: the highest displacement of the max-braking plan ``a_i = max(a - i delta, -a_max)``.

    ``v``: velocity now; ``a``: this step's command (``-a_max <= a``). Displacement from the current
    position, over every instant after now (zoh) or every substep (semi-implicit).
    """
    T = model.period
    c = _step_coeff(model)
    sa, sv = jax.lax.stop_gradient(a), jax.lax.stop_gradient(v)
    m = jnp.maximum(jnp.ceil((sa + a_max) / delta), 0.0)
    # the crossing step: larger root x of v + T (x a - delta x (x - 1) / 2) = 0, step ceil(x) - 1
    b = sa + 0.5 * delta
    disc = jnp.maximum(b * b + 2.0 * delta * sv / T, 0.0)
    x = (b + jnp.sqrt(disc)) / delta
    i0 = jnp.floor(jnp.clip(x, 0.0, m + 1.0)) - 1.0
    top = jnp.maximum(m - 1.0, 0.0)
    best = None
    for off in (0.0, 1.0, 2.0):
        i = jnp.clip(i0 + off - 1.0, 0.0, top)
        p_i, v_i = _ramp_state(i, v, a, T, delta, c)
        val = _step_max(model, p_i, v_i, jnp.maximum(a - i * delta, -a_max))
        best = val if best is None else jnp.maximum(best, val)
    p_m, v_m = _ramp_state(m, v, a, T, delta, c)
    return jnp.maximum(best, _hold_peak(model, p_m, v_m, a_max))


def velocity_threshold(v, v_max, T, delta):
    """Largest ``a`` whose max-braking plan keeps ``v <= v_max`` at every later step (closed form).

    ``min_{K >= 1} (R + delta K (K - 1) / 2) / K``, ``R = (v_max - v) / T``; the minimiser is next to
    ``sqrt(2 R / delta)`` and its neighbours are all evaluated, so rounding only lowers the result.
    """
    R = (v_max - v) / T
    k_hat = jnp.floor(jnp.sqrt(2.0 * jnp.maximum(jax.lax.stop_gradient(R), 0.0) / delta))
    best = None
    for off in (-1.0, 0.0, 1.0, 2.0):
        K = jnp.maximum(k_hat + off, 1.0)
        val = (R + delta * K * (K - 1.0) / 2.0) / K
        best = val if best is None else jnp.minimum(best, val)
    return best


# ----------------------------------------------------------------------------- one side


def _side_ok(model, d, v, a_prev, v_max, a_max, delta):
    """Whether the hardest braking the jerk allows keeps this side's position and velocity limits."""
    lo = jnp.maximum(jnp.clip(a_prev, -a_max, a_max) - delta, -a_max)
    v_ok = velocity_threshold(v, v_max, model.period, delta) >= lo
    return v_ok & (braking_peak(model, v, lo, a_max, delta) <= d)


def _upper_side(model, d, v, a_prev, v_max, a_max, delta, d_raw, v_max_raw, delta_raw):
    """(threshold, ok): the largest admissible ``a`` on the upper side, and whether it is viable.

    ``threshold`` is always inside ``[lo, hi]``, the jerk/acceleration box; where nothing passes it
    is ``lo`` (the hardest braking the jerk limit allows), the best effort. ``ok`` is ``_side_ok``
    for the unguarded limits ``d_raw``, ``v_max_raw``, ``delta_raw``. The three end-point tests run
    as one stacked evaluation (smaller program, faster compile).
    """
    ap = jnp.clip(a_prev, -a_max, a_max)
    lo = jnp.maximum(ap - delta, -a_max)
    hi = jnp.minimum(ap + delta, a_max)
    v_thr = velocity_threshold(v, v_max, model.period, delta)
    hi = jnp.maximum(jnp.minimum(hi, v_thr), lo)
    lo_raw = jnp.maximum(ap - delta_raw, -a_max)
    v_ok_raw = velocity_threshold(v, v_max_raw, model.period, delta_raw) >= lo_raw
    st = lambda *xs: jnp.stack(xs)  # noqa: E731
    peaks = braking_peak(model, st(v, v, v), st(lo, hi, lo_raw), st(a_max, a_max, a_max), st(delta, delta, delta_raw))
    ok_lo, ok_hi, ok_raw = peaks[0] <= d, peaks[1] <= d, peaks[2] <= d_raw
    s_lo, s_hi = jax.lax.stop_gradient(lo), jax.lax.stop_gradient(hi)
    s_v, s_d = jax.lax.stop_gradient(v), jax.lax.stop_gradient(d)

    def body(_, bracket):
        good, bad = bracket
        mid = 0.5 * (good + bad)
        p = braking_peak(model, s_v, mid, a_max, delta) <= s_d
        return jnp.where(p, mid, good), jnp.where(p, bad, mid)

    good, _ = jax.lax.fori_loop(0, BISECTION_STEPS, body, (s_lo, s_hi))
    # implicit-function gradient at the root: value unchanged, d(root) = -dP/dtheta / dP/da
    good_c = jnp.clip(good, lo, hi)
    peak, slope = jax.jvp(lambda a: braking_peak(model, v, a, a_max, delta), (good_c,), (jnp.ones_like(good_c),))
    slope = jax.lax.stop_gradient(slope)
    steep = slope > tiny_floor(slope.dtype)
    resid = (peak - d) - jax.lax.stop_gradient(peak - d)
    root = good_c - jnp.where(steep, resid / jnp.where(steep, slope, 1.0), 0.0)
    return jnp.where(ok_hi, hi, jnp.where(ok_lo, root, lo)), v_ok_raw & ok_raw


# ----------------------------------------------------------------------------- public entry points


def check_jerk_condition(limits: JointLimits, dt: float, integrator: str = "zoh", substeps: int = 1) -> None:
    """Raise unless the range and speed leave room for the recovery after a max-braking stop.

    The recovery from the peak of the max-braking plan (velocity 0, acceleration at worst
    ``-a_max``) ends at rest after a bounded backward travel at a bounded speed
    (``recovery_envelope``; its peak acceleration is ``<= a_max`` by construction); it must fit:
    ``v_max >= speed`` and ``q_max - q_min >= 2 travel``, with ``JERK_CONDITION_SLACK`` to spare. Skipped when the limits or ``dt`` are traced.
    """
    if limits.j_max is None:
        raise ValueError("method 'jerk'/'jerk_paper' needs JointLimits.j_max (got None)")
    if not limits.concrete or isinstance(dt, jax.core.Tracer):
        return
    A, J = np.asarray(limits.a_max, np.float64), np.asarray(limits.j_max, np.float64)
    vmax = np.asarray(limits.v_max, np.float64)
    span = np.asarray(limits.q_max, np.float64) - np.asarray(limits.q_min, np.float64)
    travel, speed, a_peak = recovery_envelope(A, J, dt)
    s = 1.0 + JERK_CONDITION_SLACK
    bad = (vmax < s * speed) | (span < 2.0 * s * travel)
    if np.any(bad):
        raise ValueError(
            "the jerk-aware bounds need room to recover from a max-braking stop (see check_jerk_condition): "
            f"joints {np.flatnonzero(np.atleast_1d(bad)).tolist()} need v_max >= {np.atleast_1d(speed * s).tolist()}, "
            f"and q_max - q_min >= {np.atleast_1d(2 * travel * s).tolist()} "
            f"with dt={dt}; got v_max={np.atleast_1d(vmax).tolist()}, q_max - q_min={np.atleast_1d(span).tolist()}, "
            f"a_max={np.atleast_1d(A).tolist()}, j_max={np.atleast_1d(J).tolist()} (raise j_max or lower a_max)"
        )


def recovery_envelope(a_max, j_max, dt):
    """Upper bounds (travel, speed, peak acceleration) of the recovery from a max-braking peak.

    At the peak ``v = 0`` and ``a >= -a_max``. Finish the step (speed ``<= a_max T``), raise ``a``
    by ``delta`` per step until it is in ``[-delta, 0)`` (``<= a_max^2 / (2 j_max)`` more speed),
    set it to 0, then stop the backward speed ``w`` with the triangle ``s (1, 2, .., N, .., 2, 1)``,
    ``N = max(ceil(sqrt(w / (delta T))), ceil(w / (a_max T)))``, ``s = w / (N^2 T) <= delta``
    (area ``w``, peak ``s N <= a_max``), then ``a = 0`` at
    rest. The speed never exceeds ``w``, so the travel is at most ``w`` times the duration.
    """
    A, J, T = np.asarray(a_max, np.float64), np.asarray(j_max, np.float64), float(dt)
    delta = J * T
    n_ramp = np.ceil(A / delta) + 1.0
    w = 2.0 * A * T + A * A / (2.0 * J)
    n_tri = np.maximum(np.ceil(np.sqrt(w / (delta * T))), np.ceil(w / (A * T)))
    a_peak = w / (n_tri * T)
    travel = w * T * (1.0 + n_ramp + 1.0 + 2.0 * n_tri)
    return travel, w, a_peak


def _jerk_inputs(q, v, a_prev, limits, dt, integrator, substeps):
    from jaxlimits._src.bounds import _state_and_limits

    model = make_model(dt, integrator, substeps)
    _check_limits_type(limits)
    if limits.j_max is None:
        raise ValueError("method 'jerk'/'jerk_paper' needs JointLimits.j_max (got None)")
    if a_prev is None:
        raise ValueError("method 'jerk'/'jerk_paper' needs a_prev (the previous acceleration)")
    a_prev = jnp.asarray(a_prev)
    q = jnp.asarray(q)
    dtype = jnp.promote_types(jnp.result_type(q, jnp.asarray(v), a_prev), jnp.float32)
    q = q.astype(dtype)
    try:
        shape = jnp.broadcast_shapes(q.shape, jnp.shape(v), a_prev.shape)
    except ValueError as exc:
        raise ValueError(f"q {q.shape}, v {jnp.shape(v)} and a_prev {a_prev.shape} do not broadcast") from exc
    q = jnp.broadcast_to(q, shape)
    q, v, q_min, q_max, v_max, a_max = _state_and_limits(q, v, limits)
    a_prev = jnp.broadcast_to(a_prev.astype(q.dtype), q.shape)
    j_max = jnp.broadcast_to(jnp.asarray(limits.j_max, q.dtype), q.shape)
    return model, q, v, a_prev, q_min, q_max, v_max, a_max, j_max


def _core(q, v, a_prev, q_min, q_max, v_max, a_max, j_max, model, rounding_guard):
    """Both sides in one pass: the lower side is stacked on a new leading axis as the mirror image."""
    inside = (q >= q_min) & (q <= q_max) & (jnp.abs(v) <= v_max) & (jnp.abs(a_prev) <= a_max)
    delta = j_max * model.period
    two = lambda x, y: jnp.stack([x, y])  # noqa: E731
    d_raw, vm_raw, dl_raw = two(q_max - q, q - q_min), two(v_max, v_max), two(delta, delta)
    a2, am2 = two(a_prev, -a_prev), two(a_max, a_max)
    dl2 = dl_raw
    if rounding_guard:
        n = getattr(model, "n", 1)
        q_min, q_max, v_max = _rounding_guard(q_min, q_max, v_max, a_max, n + 2)
        dl2 = dl_raw * (1.0 - 4.0 * jnp.finfo(q.dtype).eps)
    span = q_max - q_min
    qc = jnp.clip(q, q_min - span, q_max + span)
    v_sat = 2.0 * v_max + 4.0 * a_max * model.period
    vc = jnp.clip(v, -v_sat, v_sat)
    thr, ok = _upper_side(model, two(q_max - qc, qc - q_min), two(vc, -vc), a2, two(v_max, v_max), am2, dl2,
                          d_raw, vm_raw, dl_raw)
    viable = inside & ok[0] & ok[1]
    upper, lower = thr[0], -thr[1]
    conflict = lower > upper
    toward_upper = (v > 0) | ((v == 0) & (2.0 * q >= q_min + q_max))
    brake = jnp.where(toward_upper, upper, lower)
    return Bounds(jnp.where(conflict, brake, lower), jnp.where(conflict, brake, upper), viable)


@functools.partial(jax.jit, static_argnames=("dt", "integrator", "substeps", "rounding_guard"))
def _core_jit(q, v, a_prev, q_min, q_max, v_max, a_max, j_max, *, dt, integrator, substeps, rounding_guard):
    return _core(q, v, a_prev, q_min, q_max, v_max, a_max, j_max, make_model(dt, integrator, substeps), rounding_guard)


def jerk_acc_bounds(q, v, a_prev, limits: JointLimits, dt, integrator="zoh", substeps=1, rounding_guard=True) -> Bounds:
    """Exact jerk-aware bounds (see the module docstring); called by ``acc_bounds(method="jerk")``.

    Shapes, dtypes and the best effort on non-viable states are those of ``acc_bounds``; ``viable``
    says whether ``(q, v, a_prev)`` is viable (``is_viable_jerk``). Compiled once per static
    configuration (``dt``, ``integrator``, ``substeps``) even when called eagerly.
    """
    model, q, v, a_prev, q_min, q_max, v_max, a_max, j_max = _jerk_inputs(q, v, a_prev, limits, dt, integrator, substeps)
    check_jerk_condition(limits, model.period, integrator, substeps)
    arrays = (q, v, a_prev, q_min, q_max, v_max, a_max, j_max)
    if isinstance(model.period, jax.core.Tracer):
        return _core(*arrays, model, rounding_guard)
    return _core_jit(*arrays, dt=float(model.period), integrator=integrator, substeps=int(substeps),
                     rounding_guard=bool(rounding_guard))


def is_viable_jerk(q, v, a_prev, limits: JointLimits, dt, integrator: str = "zoh", substeps: int = 1):
    """Whether ``(q, v, a_prev)`` is viable under position, velocity, acceleration and jerk limits.

    Inside the limits (``|a_prev| <= a_max`` too) and some acceleration of the next step keeps
    the max-braking plans of both sides inside (see ``jerk_acc_bounds``). Needs ``dt`` (the jerk
    limit is per control step). Returns a bool array of the broadcast shape.
    """
    return jerk_acc_bounds(q, v, a_prev, limits, dt, integrator, substeps, rounding_guard=False).viable
