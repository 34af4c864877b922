"""When the jerk-aware bounds are exact: the range and speed the worst recovery needs (``check_jerk_condition``).

The bounds of ``jerk.py`` test each side on its own: the upper bound ``U`` is the largest command
``a`` (in the jerk box) whose max-braking plan ``B_up(a)`` (``a_i = max(a - i delta, -A)``) keeps
``q <= q_max`` and ``v <= v_max``; the lower bound ``L`` is the mirror (``B_lo(a)``,
``a_i = min(a + i delta, A)``, keeps ``q >= q_min``, ``v >= -v_max``); ``viable`` is "inside the
limits, ``B_up(lo)`` passes the upper test and ``B_lo(hi)`` the lower one". Notation:
``A = a_max``, ``delta = j_max T``, ``h = T / n`` (``n`` substeps; the zero-order hold is the
continuous-time limit, positions at every instant), ``span = q_max - q_min``.

**Reduction.** Call a state *decoupled-viable* (``D``) when it is inside the limits and both
per-side tests pass. If ``a`` is in ``[L, U]``, the next state is in ``D`` again (the tails of
``B_up(a)`` and ``B_lo(a)`` are the hardest plans from there, and they pass). So ``D`` is invariant
-- hence equal to the viability kernel and ``[L, U]`` the exact set of admissible commands --
as soon as no state of ``D`` has a *conflict* ``L > U``. (``B_up``/``B_lo`` are the pointwise
lowest/highest plans that start with ``a``, so ``a <= U`` and ``a >= L`` are necessary anyway.)

**When a conflict can happen.** At a conflict ``U < hi`` (else ``L > hi``: not in ``D``), so the
upper side binds at ``U``, and ``B_lo(U)`` fails the lower test. By the mirror symmetry
``(v, a) -> (-v, -a)`` take the upper side binding by position: ``peak(B_up(U)) = q_max``.

* *Position failure*, ``min(B_lo(U)) < q_min``: then ``span < peak(B_up(U)) - min(B_lo(U))``.
  If the peak ``t_u`` of ``B_up(U)`` comes before the trough of ``B_lo(U)``, compare ``B_lo(U)``
  with the plan ``Pi`` that follows ``B_up(U)`` to the end of the peak's step and then raises the
  acceleration at full jerk: ``B_lo(U) >= Pi`` pointwise, so the difference is at most the largest
  drop of ``Pi`` after its peak. At the peak the velocity is 0 (zoh; semi-implicit: the velocity
  after the peak substep is ``>= 0``) and the acceleration is in ``[-A, 0]``; the drop is largest
  for the lowest acceleration held for as long as possible afterwards (pointwise lower
  accelerations from the same state): ``-A`` for a full step from ``v = 0`` (zoh: the peak at a
  step's start); ``-a_w`` for the ``n - 1`` substeps after the first (semi-implicit: the peak after
  the first substep with velocity exactly 0, so the step starts at ``h a_w <= v_max``,
  ``a_w = min(A, v_max / h)``). Trough before peak is the mirror image (``B_up(U) <=`` "follow
  ``B_lo(U)`` to the end of its trough's step, then brake"). So ``span < travel``, the depth of the
  fastest recovery ``B_lo(-a_w)`` from that *worst peak state*; by the mirror image, the peak of
  the max-braking plan ``a_w, a_w - delta, ..., -A`` from ``v = 0`` (zoh) or ``v = -h a_w``.
* *Velocity failure*, ``min v(B_lo(U)) < -v_max``: ``U < 0`` (else ``B_lo`` only speeds up), so
  ``B_up(U)`` rises only if the state moves up: ``v > 0`` (zoh), ``v >= h |U|`` (semi-implicit: the
  first substep must not go down). ``B_lo(U)`` loses at most ``loss(U) = T max_K (K |U| -
  delta K (K-1)/2)`` of speed, so ``v_max < loss(U) - v <= speed``: ``speed = loss(A)`` (zoh),
  ``loss(A) - h A`` (semi-implicit; ``loss`` has slope ``>= T >= h`` in ``|U|``), and 0 when
  ``loss(A) <= 2 h A`` (then ``h |U| <= v <= v_max < loss(U) - h |U|`` is impossible, ``loss(u) - 2 h u``
  being convex and 0 at 0): the largest backward speed of the same worst recovery.
* The upper side binding by *velocity* instead (``v(B_up(U))`` reaches ``v_max``): ``U >= 0``, and
  ``B_lo(U)`` can only dip below the start if ``v < 0``, which needs ``v_max < loss(A)``; under
  ``v_max >= speed`` the semi-implicit remainder ``v in (-h A, 0)`` forces ``h U >= |v|``: no dip.

Hence ``span >= travel`` and ``v_max >= speed`` exclude every conflict: the bounds are exact.

**Tight.** Below either, a conflict state exists: ``q`` just under ``q_max`` with ``v`` just above
0 (semi-implicit: just above ``h a_w``, ``a_w`` a little lower if ``h a_w = v_max``) and
``a_prev = -a_w``. The upper side binds at ``U ~ -a_w`` and ``B_lo(U)`` is the worst recovery
itself, deeper than ``span`` (or faster than ``v_max``), while ``B_lo(-a_w + delta)``, the per-side
test, passes: the per-side tests call it viable, yet no command keeps both limits
(``tests/test_jerk_condition.py`` shows it with the LP, down to 1e-7 below the exact values). And
every span in ``(0, travel)`` has one (the same family with ``a_prev`` in ``(-a_w, 0)``).

The check adds only the float32 rounding margin of the guarded limits the bounds use
(``rounding_margin``); ``recovery_envelope`` gives the exact values.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from jaxlimits._src.tracing import is_traced

INTEGRATORS = ("zoh", "semi_implicit")
EPS32 = float(np.finfo(np.float32).eps)
GUARD_DELTA_ULPS = 4.0  # the guarded core uses delta (1 - 4 eps) (jerk._evaluate)
EXTRA_GUARD_ROUNDINGS = 2  # and 2 more roundings per step than the discretisation (jerk._evaluate)


class RecoveryEnvelope(NamedTuple):
    """The worst recovery from a max-braking peak: ``travel`` [rad] (its depth) and ``speed`` [rad/s]."""

    travel: np.ndarray
    speed: np.ndarray


def _check_discretisation(dt, integrator, substeps):
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {INTEGRATORS}, got {integrator!r}")
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"substeps must be an integer >= 1, got {substeps!r}")
    if integrator == "zoh" and substeps != 1:
        raise ValueError(f"substeps applies to integrator='semi_implicit' only, got substeps={substeps} with 'zoh'")
    T = np.asarray(dt, np.float64)
    if T.shape != () or not np.isfinite(T) or T <= 0:
        raise ValueError(f"dt must be a finite scalar > 0, got {dt!r}")
    return float(T), int(substeps)


def max_braking_peak(v0, a0, a_max, delta, T, integrator="zoh", substeps=1):
    """Highest displacement of the max-braking plan ``a_i = max(a0 - i delta, -a_max)`` from velocity ``v0``.

    Float64 NumPy, closed form (broadcasts over arrays): the ramp's step-boundary states are
    ``v_i = v0 + T (i a0 - delta i (i-1)/2)``, ``p_i = T i v0 + T^2 (a0 i(i-1)/2 - delta i(i-1)(i-2)/6)
    + c (i a0 - delta i(i-1)/2)`` (``c = T^2/2`` zoh, ``h^2 n (n+1)/2`` semi-implicit); the steps around
    the velocity's zero crossing (larger root of ``v_x = 0``) and step 0 are maximised exactly
    (zoh: the parabola's vertex, semi-implicit: the best substeps), and the hold phase (``-a_max``
    from step ``m = ceil((a0 + a_max) / delta)``) by its braking distance. Positions after now
    (zoh: every instant; semi-implicit: every substep). Units: rad, rad/s, rad/s^2, s.
    """
    v0, a0, A, delta = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in (v0, a0, a_max, delta)))
    n = int(substeps)
    h = T / n
    c = 0.5 * T * T if integrator == "zoh" else h * h * n * (n + 1) / 2.0
    m = np.maximum(np.ceil((a0 + A) / delta), 0.0)

    def state(i):
        tri = i * (i - 1.0) / 2.0
        p = T * i * v0 + T * T * (a0 * tri - delta * tri * (i - 2.0) / 3.0) + c * (i * a0 - delta * tri)
        return p, v0 + T * (i * a0 - delta * tri)

    def step_max(p, v, a):
        if integrator == "zoh":
            end = p + T * v + 0.5 * T * T * a
            inside = (v > 0) & (a < 0) & (v < -a * T)
            return np.where(inside, p - v * v / (2.0 * np.where(inside, a, -1.0)), end)
        k_star = np.where(a < 0, -v / (h * np.where(a < 0, a, -1.0)) - 0.5, float(n))
        best = np.full(p.shape, -np.inf)
        for k in (np.ones_like(p), np.full_like(p, float(n)), np.floor(k_star), np.floor(k_star) + 1.0):
            k = np.clip(k, 1.0, float(n))
            best = np.maximum(best, p + k * h * v + h * h * a * k * (k + 1.0) / 2.0)
        return best

    b = a0 + 0.5 * delta
    x = (b + np.sqrt(np.maximum(b * b + 2.0 * delta * v0 / T, 0.0))) / delta
    best = np.full(v0.shape, -np.inf)
    top = np.maximum(m - 1.0, 0.0)
    for i in (np.zeros_like(x), np.floor(x) - 2.0, np.floor(x) - 1.0, np.floor(x), np.floor(x) + 1.0):
        i = np.clip(i, 0.0, top)
        p_i, v_i = state(i)
        val = step_max(p_i, v_i, np.maximum(a0 - i * delta, -A))
        best = np.where(m > 0, np.maximum(best, val), best)
    p_m, v_m = state(m)  # the hold phase: -a_max from step m on (from now on if m = 0)
    vp = np.maximum(v_m, 0.0)
    if integrator == "zoh":
        hold = np.where((m > 0) | (v_m > 0), p_m + vp * vp / (2.0 * A), step_max(p_m, v_m, -A))
    else:
        k_hat = np.floor(vp / (A * h))
        hold = np.where(m > 0, p_m, -np.inf)  # boundary m is a real position when m > 0
        for off in (-1.0, 0.0, 1.0):
            K = np.maximum(k_hat + off, 1.0)
            hold = np.maximum(hold, p_m + h * (K * v_m - A * h * K * (K + 1.0) / 2.0))
    return np.maximum(best, hold)


def speed_loss(a_max, delta, T):
    """``T max_{K >= 1} (K a_max - delta K (K-1)/2)``: the speed ``a_max, a_max - delta, ...`` gains before it turns.

    Equivalently the backward speed the fastest recovery from ``a = -a_max`` (at rest) reaches. [rad/s]
    """
    A, delta = np.broadcast_arrays(np.asarray(a_max, np.float64), np.asarray(delta, np.float64))
    k_hat = np.floor(A / delta + 0.5)
    best = np.full(A.shape, -np.inf)
    for off in (-1.0, 0.0, 1.0):
        K = np.maximum(k_hat + off, 1.0)
        best = np.maximum(best, K * A - 0.5 * delta * K * (K - 1.0))
    return T * best


def recovery_envelope(a_max, j_max, dt, integrator="zoh", substeps=1, v_max=None) -> RecoveryEnvelope:
    """Depth and backward speed of the worst recovery from a max-braking peak: the exact condition.

    Args: ``a_max`` [rad/s^2], ``j_max`` [rad/s^3] and ``v_max`` [rad/s] (arrays, broadcast; ``v_max``
    only matters for the semi-implicit model, ``None``: no limit), ``dt`` [s] the control period,
    ``integrator``/``substeps`` as in ``acc_bounds``.

    The worst peak state (module docstring): velocity 0 at the start of a step whose acceleration is
    ``-a_max`` (zoh), or velocity ``h a_w`` before a step of ``-a_w``, 0 after its first substep
    (semi-implicit, ``h = dt / substeps``, ``a_w = min(a_max, v_max / h)``: the step starts at
    ``h a_w <= v_max``). The fastest recovery from there raises the acceleration by
    ``delta = j_max dt`` per step up to ``a_max``; every recovery stays above it. Below
    the peak it reaches ``travel`` [rad] (by the mirror image: the peak of the max-braking plan
    ``a_w, a_w - delta, ..., -a_max`` from velocity 0, resp. ``-h a_w``; ``max_braking_peak``).
    ``speed`` [rad/s]: zoh ``speed_loss`` (the recovery's backward speed); semi-implicit
    ``speed_loss - h a_max`` where that exceeds ``h a_max`` (else 0: no state can be moving up fast
    enough to peak while that recovery is too fast). The per-side bounds are exact for every state if
    and only if ``q_max - q_min >= travel`` and ``v_max >= speed``.
    """
    T, n = _check_discretisation(dt, integrator, substeps)
    A, J, V = np.broadcast_arrays(
        np.asarray(a_max, np.float64),
        np.asarray(j_max, np.float64),
        np.asarray(np.inf if v_max is None else v_max, np.float64),
    )
    return _envelope(A, J * T, V, T, integrator, n)


def _envelope(A, delta, v_max, T, integrator, n) -> RecoveryEnvelope:
    h = T / n
    if integrator == "zoh":
        travel = max_braking_peak(np.zeros_like(A), A, A, delta, T, integrator, n)
        return RecoveryEnvelope(travel, speed_loss(A, delta, T))
    a_w = np.minimum(A, v_max / h)
    travel = max_braking_peak(-h * a_w, a_w, A, delta, T, integrator, n)
    loss = speed_loss(A, delta, T)
    return RecoveryEnvelope(travel, np.where(loss > 2.0 * h * A, loss - h * A, 0.0))


def rounding_margin(limits, T, integrator, n):
    """What the float32 rounding guard of ``jerk._evaluate`` takes from the range and ``v_max``.

    The guarded bounds work on ``q_min + m``, ``q_max - m``, ``v_max (1 - R eps)`` and
    ``delta (1 - 4 eps)`` (``joint_state.guard_limits``, ``R = 2 + r (1 + stop_steps)`` with ``r`` the
    discretisation's roundings per step plus 2, ``stop_steps = ceil(v_max / (A T)) + ceil(3 A / delta) + 1``,
    ``m = R eps (max|q_lim| + 2 v_max^2 / A)``); the condition must hold for those too. float32 ``eps``
    (the larger one; float64 needs ~1e-9 of this). Returns ``(range taken, relative v_max taken, delta factor)``.
    """
    q_min, q_max, v_max, A, J = (
        np.asarray(getattr(limits, f), np.float64) for f in ("q_min", "q_max", "v_max", "a_max", "j_max")
    )
    delta = J * T
    roundings = (3 if integrator == "zoh" else n) + EXTRA_GUARD_ROUNDINGS
    stop_steps = np.ceil(v_max / (A * T)) + np.ceil(3.0 * A / delta) + 1.0
    R = EPS32 * (2.0 + roundings * (1.0 + stop_steps))
    m_q = R * (np.maximum(np.abs(q_min), np.abs(q_max)) + 2.0 * v_max * v_max / A)
    return 2.0 * m_q, R, 1.0 - GUARD_DELTA_ULPS * EPS32


def jerk_condition_needs(limits, dt, integrator="zoh", substeps=1):
    """``(span_needed, v_max_needed, exact)`` per joint [rad, rad/s]: the exact envelope plus the rounding margin.

    ``exact`` is ``recovery_envelope``; the needed values add ``rounding_margin`` (and 16 float32
    ulps for the rounding of the limits themselves), so that the guarded float32 limits still
    satisfy the exact condition.
    """
    T, n = _check_discretisation(dt, integrator, substeps)
    A, J, V = np.broadcast_arrays(*(np.asarray(getattr(limits, f), np.float64) for f in ("a_max", "j_max", "v_max")))
    exact = _envelope(A, J * T, V, T, integrator, n)
    taken, rel_v, delta_factor = rounding_margin(limits, T, integrator, n)
    guarded = _envelope(A, J * T * delta_factor * (1.0 - 2.0 * EPS32), V, T, integrator, n)
    slack = 1.0 + 16.0 * EPS32
    span_needed = np.maximum(guarded.travel, exact.travel) * slack + taken
    v_needed = np.maximum(guarded.speed, exact.speed) * slack / (1.0 - rel_v)
    return span_needed, v_needed, exact


def check_jerk_condition(limits, dt, integrator: str = "zoh", substeps: int = 1) -> None:
    """Raise ``ValueError`` unless the jerk-aware bounds are exact for these limits (and not just per side).

    Args: ``limits`` (``JointLimits`` with ``j_max``; [rad], [rad/s], [rad/s^2], [rad/s^3]), ``dt`` the
    control period [s], ``integrator``/``substeps`` the discretisation.

    Needs, per joint, ``q_max - q_min >= travel`` and ``v_max >= speed`` of ``recovery_envelope``:
    the depth and the backward speed of the fastest recovery from the worst peak of a max-braking
    stop (module docstring: under these the upper- and lower-side tests never conflict, so they are
    the exact viability test; below either, a state exists that they call viable and is not). Plus
    the float32 rounding margin of the guarded limits (``jerk_condition_needs``; 1e-5 to 1e-4 of
    the range). The message names the joints, the fields, the values and the needed values. Skipped
    when the limits or ``dt`` are traced (nothing to check eagerly).
    """
    if getattr(limits, "j_max", None) is None:
        raise ValueError("the jerk-aware bounds need JointLimits.j_max (got None)")
    if not limits.concrete or is_traced(dt):
        _check_discretisation(1.0, integrator, substeps)
        return
    T, n = _check_discretisation(dt, integrator, substeps)
    fields = tuple(np.asarray(getattr(limits, name), np.float64) for name in _FIELDS)
    message = _verdict(tuple((x.shape, x.tobytes()) for x in fields), T, integrator, n)
    if message is not None:
        raise ValueError(message)


_FIELDS = ("q_min", "q_max", "v_max", "a_max", "j_max")


@functools.lru_cache(maxsize=256)
def _verdict(key, dt, integrator, substeps):
    """None, or the error message; cached per configuration (eager calls check it at every step: ~1 ms uncached)."""
    f = {name: np.frombuffer(raw, np.float64).reshape(shape) for name, (shape, raw) in zip(_FIELDS, key)}
    limits = _Fields(**f)
    span_needed, v_needed, _ = jerk_condition_needs(limits, dt, integrator, substeps)
    span, vmax, span_needed, v_needed, A, J = (
        np.atleast_1d(x)
        for x in np.broadcast_arrays(f["q_max"] - f["q_min"], f["v_max"], span_needed, v_needed, f["a_max"], f["j_max"])
    )
    short_span, short_v = span < span_needed, vmax < v_needed
    if not np.any(short_span | short_v):
        return None
    lines = []
    for j in np.flatnonzero(short_span | short_v):
        parts = [f"q_max - q_min = {span[j]:.6g} < {span_needed[j]:.6g} needed"] if short_span[j] else []
        parts += [f"v_max = {vmax[j]:.6g} < {v_needed[j]:.6g} needed"] if short_v[j] else []
        lines.append(f"joint {j}: " + ", ".join(parts) + f" (a_max={A[j]:.6g}, j_max={J[j]:.6g})")
    return (
        "the jerk-aware bounds are exact only with room to recover from the worst max-braking stop "
        f"(check_jerk_condition; dt={dt!r}, integrator={integrator!r}, substeps={substeps}): "
        + "; ".join(lines)
        + ". The recovery needs the range and v_max above (raise j_max, lower a_max, or shorten dt)."
    )


class _Fields(NamedTuple):
    q_min: np.ndarray
    q_max: np.ndarray
    v_max: np.ndarray
    a_max: np.ndarray
    j_max: np.ndarray
