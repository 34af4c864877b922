"""Jerk-aware acceleration bounds: the state is ``(q, v, a_prev)`` and ``|a_k - a_{k-1}| <= j_max dt``.

Derivation (``docs/jerk.md`` has the long form). Work on the upper side with ``d = q_max - q``;
the lower side is the mirror (``d = q - q_min``, ``v -> -v``, ``a_prev -> -a_prev``, negated).
Write ``A = a_max``, ``delta = j_max T`` (the largest change of acceleration per control step).

* **Max braking is pointwise lowest.** If the command of this step is ``a_0 = a``, every admissible
  future has ``a_i >= max(a - i delta, -A)`` (induction on the jerk limit), hence velocities and
  positions (at every instant for zoh, every substep for the semi-implicit model) at least those of
  the *max-braking* plan ``B(a)``: ``a_i = max(a - i delta, -A)``. So ``peak_B(a) <= d`` and
  ``vpeak_B(a) <= v_max`` are *necessary* for ``a`` to be admissible.
* **And sufficient** when the range and speed leave room for the fastest recovery from the worst
  peak state (``check_jerk_condition``, ``jerk_condition.py``; tight: just below it a state the
  per-side tests call viable has no admissible command, measured against the LP). Then the
  upper-side and lower-side conditions can be checked separately, exactly as Del Prete's condition
  (11) decouples them without jerk; the long-horizon LP in the tests (which couples everything)
  confirms it. So the exact upper bound is the largest ``a`` in the jerk/acceleration box with
  ``vpeak_B(a) <= v_max`` and ``peak_B(a) <= d``.
* **Velocity threshold, closed form.** ``vpeak_B(a) - v = T sum_i max(a - i delta, 0) =
  T max_{K >= 1} (K a - delta K (K - 1) / 2)``, so the threshold is
  ``min_{K >= 1} (R + delta K (K - 1) / 2) / K`` with ``R = (v_max - v) / T``; the minimising
  integer is next to ``sqrt(2 R / delta)`` (the paper's eqs. 13-14 happen to be exact here).
* **Peak, closed form.** ``peak_B(a)`` (``braking_peak``) is nondecreasing in ``a`` (pointwise
  larger accelerations). In the ramp phase (``i < m``, ``m = ceil((a + A) / delta)``) the
  step-boundary states are

      v_i = v + T (i a - delta i (i - 1) / 2),
      p_i = T i v + T^2 (a i (i - 1) / 2 - delta i (i - 1) (i - 2) / 6) + c (i a - delta i (i - 1) / 2),

  with ``c = T^2 / 2`` (zoh) or ``h^2 n (n + 1) / 2`` (semi-implicit, ``h = T / n``); the step in
  which the velocity crosses zero is next to the larger root of the quadratic ``v_x = 0``; three
  candidate steps are evaluated exactly (continuous-time interior maximum for zoh, the best
  substeps for the semi-implicit model). In the hold phase (``a = -A`` from step ``m`` on) the
  peak is ``p_m + v_m^2 / (2 A)`` (zoh) or ``p_m + D(v_m)`` (the semi-implicit discrete braking
  distance of ``semi_implicit.py``). Every value taken is a real position of ``B(a)``.
* **Position threshold, closed form** (``position_threshold``). For a fixed ramp length every
  position of the plan is linear in ``a`` with a nonnegative slope, and any plan whose
  accelerations are ``a - i delta`` or ``-A`` lies pointwise below ``B(a)``: the largest ``a``
  keeping one of its positions at most ``d`` is an *upper bound* of the threshold, and the
  threshold is the minimum of these roots over all positions. The minimum is reached at the peak
  of the active structure, so evaluating the structures around it gives the exact value: (i) the
  endless ramp ``a_i = a - i delta`` in the step where the velocity crosses zero (zoh: the root
  over the step is ``delta i - V'^2 / (2 D')`` at the interior minimiser, else an end; the
  semi-implicit substeps lie on ``p(t) + h (v(t) - v) / 2``, minimiser from a quadratic, its two
  integer neighbours), and (ii) the hold phase for each ramp length ``m`` of the box (zoh: a
  quadratic in ``v_m``; semi-implicit: the active line of ``D``, itself a quadratic). The crossing
  step at the threshold is ``floor(x)`` with ``x`` the largest root of the depressed cubic
  ``x^3 + (6 v / (delta T) - 1) x - 12 d' / (delta T^2) = 0`` (the peak when the velocity vanishes at
  the step boundary ``x`` is ``T x v / 2 + delta T^2 (x^3 - x) / 12``, monotone in ``x``;
  ``d' = d + h v / 2`` semi-implicit), found by ``NEWTON_STEPS`` Newton steps from an upper
  bound (it stays above the root, by < 1); steps ``floor(x) - 1``, ``floor(x)`` and step 0 are
  evaluated. No loop, no bisection: 16 divisions (semi-implicit 22) per side in one vectorised pass.
* **Safety net, gradient.** The minimum is lowered by a rounding margin (``NUDGE_ULPS`` ulps of
  ``2 A``, and ``PEAK_ULPS`` ulps of the peak's terms over a lower bound of ``dP/da``, for where the
  peak is flat in ``a``), clipped to the box ``[max(a_prev - delta, -A), min(a_prev + delta, A,
  v-threshold)]`` and *verified* with ``braking_peak``: only a value that passes is returned, else
  the hardest braking ``max(a_prev - delta, -A)``. Its gradient is the implicit-function one
  (``-dP/dtheta / dP/da`` at the root, ``_implicit_root``).
* **XLA on the CPU.** Each side is one elementwise chain, not stacked with the other (a stacked
  input is a concatenation, read element by element), and ends in ``safe_math.materialize`` (``Jerk.fuse_sides``):
  five loops in all instead of ~60.
"""

from __future__ import annotations

import functools


import jax
import jax.numpy as jnp

from jaxlimits._src.jerk_condition import check_jerk_condition
from jaxlimits._src.joint_state import JointArrays, check_limits_type, guard_limits, inside_limits, joint_arrays
from jaxlimits._src.limit import AccelerationLimit, Bounds, Terms, combine, nan_state_rule, toward_upper_side
from jaxlimits._src.safe_math import tiny_floor
from jaxlimits._src.tracing import is_traced

NUDGE_ULPS = 32  # rounding margin of the threshold, ulps of 2 a_max
PEAK_ULPS = 4  # and ulps of the peak's terms, through dP/da (see _upper_side)
NEWTON_STEPS = 3


# ----------------------------------------------------------------------------- the braking plan


def _ramp_state(i, v, a, T, delta, c):
    """Displacement and velocity at the start of step ``i`` of the ramp ``a_j = a - j delta``."""
    tri = i * (i - 1.0) / 2.0
    p = T * i * v + T * T * (a * tri - delta * tri * (i - 2.0) / 3.0) + c * (i * a - delta * tri)
    return p, v + T * (i * a - delta * tri)


def braking_peak(model, v, a, a_max, delta):
    """``peak_B(a)``: the highest displacement of the max-braking plan ``a_i = max(a - i delta, -a_max)``.

    ``v``: velocity now; ``a``: this step's command (``-a_max <= a``). Displacement from the current
    position, over every instant after now (zoh) or every substep (semi-implicit).
    """
    T = model.period
    c = model.position_gain
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
        val = model.step_peak(p_i, v_i, jnp.maximum(a - i * delta, -a_max))
        best = val if best is None else jnp.maximum(best, val)
    p_m, v_m = _ramp_state(m, v, a, T, delta, c)
    # the hold phase: a = -a_max from step m on, the discretisation's braking distance
    return jnp.maximum(best, p_m + model.braking_distance(v_m, a_max))


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


# ----------------------------------------------------------------------------- the position threshold


def _crossing_step(p, q):
    """The largest root of ``x^3 + p x + q = 0`` (0 if none is positive), from above, to well within 1.

    Newton's iteration from an upper bound decreases monotonically to the largest root (the cubic
    is convex for ``x > 0``). The start: with ``s = sqrt(-p)``, ``c = cbrt(-q)`` the root is in
    ``[M, 1.3248 M]``, ``M = max(s, c)``, when ``p < 0 <= -q`` (``1.3248^3 >= 1.3248 + 1``); in
    ``[0.6823 U, U]``, ``U = min(c, c^3 / p)``, when ``p >= 0``; at most ``s`` when ``q > 0``.
    ``NEWTON_STEPS`` steps leave it above the root by a small fraction (measured < 0.01 after 3).
    Only selects integers: no transcendental function but ``exp``/``log`` (cheap on XLA's CPU).
    """
    s = jnp.sqrt(jnp.maximum(-p, 0.0))
    mq = jnp.maximum(-q, tiny_floor(q.dtype))
    c = jnp.exp(jnp.log(mq) / 3.0)
    x = jnp.where(
        p < 0,
        jnp.where(q < 0, 1.3248 * jnp.maximum(s, c), s),
        jnp.where(q < 0, jnp.minimum(c, mq / jnp.maximum(p, tiny_floor(p.dtype))), 0.0),
    )
    for _ in range(NEWTON_STEPS):
        g = (x * x + p) * x + q
        slope = 3.0 * x * x + p
        x = jnp.clip(x - g / jnp.maximum(slope, tiny_floor(p.dtype)), 0.0, x)
    return x


def _ramp_root(model, d, v, delta, i):
    """Largest ``a`` keeping every position of step ``i`` of the endless ramp ``a_j = a - j delta`` at most ``d``.

    Positions are linear in ``a``: ``p(t) = v t + a t^2/2 - delta S(t)``, ``S(t) = sum_{k=1..i} (t - kT)^2 / 2``
    on ``t in [iT, (i+1)T]``, so the bound at ``t`` is ``(D' - V' t + delta i t^2/2) / (t^2/2)`` with
    ``V' = v + delta T i (i+1)/2``, ``D' = d + delta T^2 i (i+1) (2i+1)/12``; zoh: minimised over the
    step at ``t* = 2 D' / V'`` (value ``delta i - V'^2 / (2 D')``) if inside, else at its end (its
    start is the previous candidate's end). Semi-implicit: positions at substeps ``K`` are
    ``p(Kh) + h (v(Kh) - v) / 2``, bound ``2 N(Kh) / (h^2 K (K+1))``,
    continuous minimiser ``t* = (D3 + sqrt(D3^2 + V' D3 h)) / V'`` and its two integer neighbours.
    Step 0 excludes the start (``v <= 0``: its end). Every value is an upper bound of the threshold.
    """
    T = model.period
    s1 = T * i * (i + 1.0) / 2.0
    Vp = v + delta * s1
    s2 = T * T * i * (i + 1.0) * (2.0 * i + 1.0) / 12.0
    return model.ramp_roots(d, v, delta, i, Vp, s1, s2)


def _hold_root(model, d, v, a_max, delta, m):
    """Largest ``a`` keeping the hold phase of ``a_j = a - j delta`` (``j < m``), ``-a_max`` after, at most ``d``.

    ``p_m = P0 + sp a`` and ``v_m = V0 + T m a`` (ramp formulas); zoh: ``p_m + v_m^2 / (2 A) = d`` is
    a quadratic, solved for ``x = v_m`` as ``2 A C / (A r + sqrt(A^2 r^2 + 2 A C))``, ``r = sp/(T m)``,
    ``C = d - P0 + r V0`` (``C < 0``: ``x = 0``). Semi-implicit: ``p_m + D(v_m)``, ``D`` the maximum of
    the lines ``h (j x - A h j (j+1)/2)``; the active ``j`` is the largest with ``C0 + r A h j +
    A h^2 j (j-1)/2 <= d`` (a quadratic), it and its neighbours are solved exactly (``min``).
    Every value is an upper bound of the threshold (that plan is pointwise below the max-braking one).
    """
    T = model.period
    c = model.position_gain
    sv = T * m
    sp = T * T * m * (m - 1.0) / 2.0 + c * m
    tri = m * (m - 1.0) / 2.0
    V0 = v - delta * T * tri
    P0 = T * m * v - delta * (T * T * tri * (m - 2.0) / 3.0 + c * tri)
    r = 0.5 * T * (m - 1.0) + c / T  # sp / sv
    return model.hold_roots(d, a_max, P0, V0, r, sp, sv)


def position_threshold(model, d, v, a_max, delta, lo):
    """``sup {a >= lo : peak_B(a) <= d}`` in closed form (no gradient; see the module docstring).

    The minimum of exact per-structure roots, each an upper bound (a position of a plan pointwise
    below ``B(a)``), among them the active structure: the ramp step where the velocity crosses zero
    (``_crossing_step``; that step, the one before and step 0) and the hold phase for every ramp
    length ``m`` of the box ``[lo, lo + 2 delta]``. One chain of minima: each root feeds one
    operation, so XLA keeps the whole search in one loop.
    """
    T = model.period
    d_x = model.crossing_distance(d, v)
    i0 = jnp.floor(_crossing_step(6.0 * v / (delta * T) - 1.0, -12.0 * d_x / (delta * T * T)))
    roots = []
    for i in (jnp.zeros_like(i0), jnp.maximum(i0 - 1.0, 1.0), jnp.maximum(i0, 1.0)):
        roots += _ramp_root(model, d, v, delta, i)  # x is above x_c by < 1: floor(x_c) is i0 or i0 - 1
    m0 = jnp.maximum(jnp.ceil((lo + a_max) / delta), 1.0)
    for off in (0.0, 1.0, 2.0):
        roots += _hold_root(model, d, v, a_max, delta, m0 + off)
    best = roots[0]
    for value in roots[1:]:
        best = jnp.minimum(best, value)
    return best


def _implicit_root(model, a, v, d, a_max, delta):
    """``a`` (a root of ``braking_peak(v, a) = d`` up to rounding) with the implicit-function derivative.

    Value: ``a`` itself. Derivative: ``(dd - dP/dv dv - dP/dA dA - dP/ddelta ddelta) / (dP/da)``
    (zero where ``dP/da`` vanishes); the forward pass evaluates nothing more.
    """

    @jax.custom_jvp
    def root(a, v, d, a_max, delta):
        return a

    @root.defjvp
    def root_jvp(primals, tangents):
        a, v, d, a_max, delta = primals
        _, tv, td, ta, tdl = tangents
        peak = lambda a_, v_, am_, dl_: braking_peak(model, v_, a_, am_, dl_)  # noqa: E731
        _, lin = jax.linearize(peak, a, v, a_max, delta)
        zero = lambda x: jnp.zeros(jnp.shape(x), jnp.result_type(x))  # noqa: E731
        dp_theta = lin(zero(a), tv, ta, tdl)
        slope = jax.lax.stop_gradient(lin(jnp.ones_like(a), zero(v), zero(a_max), zero(delta)))
        steep = slope > tiny_floor(slope.dtype)
        return a, jnp.where(steep, (td - dp_theta) / jnp.where(steep, slope, 1.0), 0.0)

    return root(a, v, d, a_max, delta)


# ----------------------------------------------------------------------------- one side


def _side_ok(model, d, v, a_prev, v_max, a_max, delta):
    """Whether the hardest braking the jerk allows keeps this side's position and velocity limits.

    The velocity part is ``velocity_threshold >= lo`` written without divisions: the plan's peak
    velocity ``v + T max_{K >= 1} (K lo - delta K (K-1)/2) <= v_max``, the concave maximum next to
    ``K = lo / delta + 1/2`` (three integers evaluated).
    """
    T = model.period
    lo = jnp.maximum(jnp.clip(a_prev, -a_max, a_max) - delta, -a_max)
    k_hat = jnp.floor(lo / delta + 0.5)
    gain = None
    for off in (-1.0, 0.0, 1.0):
        K = jnp.maximum(k_hat + off, 1.0)
        val = K * lo - 0.5 * delta * K * (K - 1.0)
        gain = val if gain is None else jnp.maximum(gain, val)
    return (v + T * gain <= v_max) & (braking_peak(model, v, lo, a_max, delta) <= d)


def upper_terms(model, d, v, a_prev, v_max, a_max, delta) -> dict:
    """The upper side's terms: ``{"acceleration": hi0, "velocity": v-threshold, "position": verified root}``.

    ``hi0 = min(a_prev + delta, a_max)`` is the top of the box the jerk lets this step reach (its
    bottom ``lo = max(a_prev - delta, -a_max)`` is the lower side's ``"acceleration"`` term, and
    ``combine`` clips into ``[lo, hi0]``); ``hi`` is that box cut at the velocity threshold. The position
    threshold ``r`` (``position_threshold``) is lowered by a rounding margin (``NUDGE_ULPS``,
    ``PEAK_ULPS``), clipped to the box and *verified* (``braking_peak <= d``: the value is
    returned only if it passes); where it fails the result is ``lo`` (the hardest braking the
    jerk limit allows), the best effort. Its gradient is the implicit-function one
    (``_implicit_root``); at ``hi`` or ``lo``, theirs. The side's bound, ``clip(min(terms), lo, hi0)``,
    is then ``hi``, the root or ``lo``.
    """
    ap = jnp.clip(a_prev, -a_max, a_max)
    lo = jnp.maximum(ap - delta, -a_max)
    hi0 = jnp.minimum(ap + delta, a_max)
    v_thr = velocity_threshold(v, v_max, model.period, delta)
    hi = jnp.maximum(jnp.minimum(hi0, v_thr), lo)
    sg = jax.lax.stop_gradient
    s_lo, s_hi, s_v, s_d, s_am, s_dl = (sg(x) for x in (lo, hi, v, d, a_max, delta))
    r = position_threshold(model, s_d, s_v, s_am, s_dl, s_lo)
    # rounding margin: NUDGE_ULPS ulps of 2 a_max (the formulas' own rounding), and PEAK_ULPS ulps of
    # the peak's terms |d| + |v| t + A t^2 over a lower bound of dP/da: where the peak is flat in a
    # (few unsaturated steps, small T), its rounding moves the root by far more than ulps of a.
    # Bounds: the peak comes at t >= max(T, |v|/A); at least m0 = m(lo) steps are unsaturated, so
    # dP/da >= t^2/2 (t <= m0 T) or m0 T (t - m0 T/2).
    T = model.period
    eps = jnp.finfo(r.dtype).eps
    t = jnp.maximum(T, jnp.abs(s_v) / s_am)
    m0T = jnp.maximum(jnp.ceil((s_lo + s_am) / s_dl), 1.0) * T
    slope = jnp.where(t <= m0T, 0.5 * t * t, m0T * (t - 0.5 * m0T))
    terms = jnp.abs(s_d) + jnp.abs(s_v) * t + s_am * t * t
    r = r - eps * (2.0 * NUDGE_ULPS * s_am + PEAK_ULPS * terms / slope)
    cand = jnp.clip(r, s_lo, s_hi)
    passes = braking_peak(model, s_v, cand, s_am, s_dl) <= s_d
    at_hi = passes & (r >= s_hi)
    inner = passes & (cand > s_lo) & ~at_hi
    root = _implicit_root(model, jnp.where(inner, cand, s_lo), v, d, a_max, delta)
    return {"acceleration": hi0, "velocity": v_thr, "position": jnp.where(at_hi, hi, jnp.where(inner, root, lo))}


def _evaluate(a: JointArrays, model, rounding_guard: bool, thresholds: bool = True) -> Terms:
    """Both sides as separate elementwise chains (the lower one is the mirror image of the upper one).

    Not stacked on a new axis: a stacked input is a concatenation, which XLA's CPU loops read
    element by element (not vectorised, ~10x slower). ``thresholds=False``: only ``viable`` (the
    terms are empty).
    """
    q, v, a_prev, q_min, q_max, v_max, a_max, j_max = a
    delta = j_max * model.period
    v_sat = 2.0 * v_max + 4.0 * a_max * model.period
    vc = jnp.clip(v, -v_sat, v_sat)
    ok_up = _side_ok(model, q_max - q, vc, a_prev, v_max, a_max, delta)
    ok_lo = _side_ok(model, q - q_min, -vc, -a_prev, v_max, a_max, delta)
    viable = inside_limits(a) & ok_up & ok_lo
    if not thresholds:
        return Terms({}, {}, viable, viable)
    if rounding_guard:
        # the roundings of a whole stop (see joint_state.guard_limits): per step the discretisation's own plus
        # two of the jerk ramp; the stop is the velocity phase plus the jerk-limited swing of the acceleration
        # from +a_max to -a_max and back to 0
        stop_steps = jnp.ceil(v_max / (a_max * model.period)) + jnp.ceil(3.0 * a_max / delta) + 1.0
        q_min, q_max, v_max = guard_limits(q_min, q_max, v_max, a_max, model.roundings_per_step + 2, stop_steps)
        delta = delta * (1.0 - 4.0 * jnp.finfo(q.dtype).eps)
        v_sat = 2.0 * v_max + 4.0 * a_max * model.period
        vc = jnp.clip(v, -v_sat, v_sat)
    span = q_max - q_min
    qc = jnp.clip(q, q_min - span, q_max + span)
    upper = upper_terms(model, q_max - qc, vc, a_prev, v_max, a_max, delta)
    lower = {k: -t for k, t in upper_terms(model, qc - q_min, -vc, -a_prev, v_max, a_max, delta).items()}
    return Terms(upper, lower, viable, toward_upper_side(v=v, q=q, q_min=q_min, q_max=q_max))


_evaluate_jit = jax.jit(_evaluate, static_argnames=("model", "rounding_guard", "thresholds"))


@functools.partial(jax.jit, static_argnames=("model", "rounding_guard"))
def _bounds_jit(a: JointArrays, *, model, rounding_guard: bool):
    return nan_state_rule(combine(_evaluate(a, model, rounding_guard), fuse_sides=True), a.q, a.v, a.a_prev)


class Jerk(AccelerationLimit):
    """Exact jerk-aware bounds (module docstring) for the state ``(q, v, a_prev)``; ``viable``: ``is_viable_jerk``.

    Needs ``limits.j_max``; the room-to-recover condition (``check_jerk_condition``) is checked here.
    Compiled once per configuration (discretisation, ``rounding_guard``) even when called eagerly, and
    the same compiled function serves a call inside ``jit``: eager and jitted results are bit-identical.
    """

    needs_a_prev = True
    fuse_sides = True
    guarantees_safety = True

    def __init__(self, limits, model, rounding_guard: bool = True):
        check_limits_type(limits)
        check_jerk_condition(limits, model.period, model.integrator, model.substeps)
        self.limits, self.model, self.rounding_guard = limits, model, bool(rounding_guard)

    def _run(self, q, v, a_prev, thresholds):
        a = jerk_arrays(q, v, a_prev, self.limits)
        if is_traced(self.model.period):
            return _evaluate(a, self.model, self.rounding_guard, thresholds)
        return _evaluate_jit(a, model=self.model, rounding_guard=self.rounding_guard, thresholds=thresholds)

    def evaluate(self, q, v, a_prev=None) -> Terms:
        return self._run(q, v, a_prev, True)

    def bounds(self, q, v, a_prev=None) -> Bounds:
        if is_traced(self.model.period):
            return super().bounds(q, v, a_prev)
        a = jerk_arrays(q, v, a_prev, self.limits)
        return _bounds_jit(a, model=self.model, rounding_guard=self.rounding_guard)

    def viable(self, q, v, a_prev=None):
        return self._run(q, v, a_prev, False).viable


def jerk_arrays(q, v, a_prev, limits) -> JointArrays:
    """``joint_arrays`` with the jerk state and limit required (eager ``ValueError`` naming what is missing)."""
    check_limits_type(limits)
    if limits.j_max is None:
        raise ValueError("the jerk-aware bounds need JointLimits.j_max (got None)")
    if a_prev is None:
        raise ValueError("the jerk-aware bounds need a_prev (the previous joint accelerations)")
    return joint_arrays(q, v, limits, a_prev)
