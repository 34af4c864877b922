"""Plain scalar-Python joint acceleration bounds, one joint at a time (``math`` only).

What it is for:

* the **timing reference** of ``benchmarks/bench_bounds.py``: what the bounds cost when written as
  ordinary Python, the way a controller loop would do it without JAX;
* an **independent transcription of Del Prete 2018** used by ``tests/test_scalar_reference.py``:
  for ``integrator="zoh"`` and ``method="viability"`` it follows the paper's Algorithms 1, 2 and 3
  line by line as printed (same variable names, same branches, the same closed forms, including
  the paper's quadratic-formula root (28), which jaxlimits replaces by a cancellation-free form),
  instead of the upper-side/mirror formulation of ``jaxlimits/_src/zoh.py``.

Scope: only states in the viability kernel are meant to be passed. There is no rounding guard, no
saturation of far-out states and no best-effort resolution of conflicting bounds (``acc_bounds``
collapses a conflicting interval to a braking action; this reference returns it as computed).

Divisions by zero. The only divisions of Algorithms 1-3 that can have a zero denominator are
Alg. 1 lines 2 and 4, ``-v^2 / (2 (q_max - q))`` and ``v^2 / (2 (q - q_min))``, at a state exactly
on a position limit. There the quotient is replaced by the value IEEE-754 division would give for a
nonzero numerator (``-inf`` for line 2, ``+inf`` for line 4), and by ``0`` for ``0/0`` (the state
at rest on the limit, where ``-v^2/(2d)`` is 0 along ``v = 0``); see ``_div``. For viable states
these substitutes are never the selected bound except at rest on the limit, where they give the
correct answer 0 (``min(q1M, q2M) = min(0, 0)``). Every other denominator is ``dt``, ``dt^2``,
``2 a = 2 dt^2``, ``a_max`` or a positive integer expression, all > 0.

Reading of Alg. 1: the listing nests lines 13-17 (``q̈UB <- q̈3M`` and the ``if q̈3m < q̈1M``
test) in the ``else`` branch of ``if q̇ >= 0`` (the branch for negative velocity, mirror image of
lines 7-11). Read flat instead, the test would also run for ``q̇ >= 0``; for viable states it then
selects ``q̈3m`` again (``q̈3m < q̈1M`` iff ``2 (q - q_min) > -dt q̇``), except at rest on
``q_min`` where both readings give 0, so the two readings agree.

``integrator="semi_implicit"`` is a scalar port of ``jaxlimits/_src/semi_implicit.py``
(``position_upper``, ``viability_upper`` and ``end_position_upper``), applied to the lower side
by the mirror rule ``lower(q, v) = -upper(-q, -v)`` with the limits swapped, as ``bounds.py`` does.
``method="naive"`` is eq. (2) (for ``semi_implicit``: the end-of-step position of the substep
recursion in place of the zero-order hold's).
"""

from __future__ import annotations

import math

__all__ = [
    "acc_bounds_from_pos_limits",
    "acc_bounds_from_viability",
    "scalar_bounds",
    "semi_implicit_upper",
]


def _div(num, den, zero_over_zero=0.0):
    """``num / den``, with ``den == 0`` mapped to the signed infinity (or ``zero_over_zero`` for 0/0)."""
    if den != 0.0:
        return num / den
    if num == 0.0:
        return zero_over_zero
    return math.copysign(math.inf, num) * math.copysign(1.0, den)


# ------------------------------------------------------------------ zero-order hold: the paper


def acc_bounds_from_pos_limits(q, dq, q_min, q_max, dt):
    """Del Prete 2018, Algorithm 1 (accBoundsFromPosLimits), literally. Returns ``(LB, UB)``."""
    ddq1_M = -dq / dt  # line 1
    ddq2_M = _div(-dq * dq, 2.0 * (q_max - q))  # line 2
    ddq3_M = 2.0 * (q_max - q - dt * dq) / (dt * dt)  # line 3
    ddq2_m = _div(dq * dq, 2.0 * (q - q_min))  # line 4
    ddq3_m = 2.0 * (q_min - q - dt * dq) / (dt * dt)  # line 5
    if dq >= 0.0:  # line 6
        ddq_LB = ddq3_m  # line 7
        if ddq3_M > ddq1_M:  # line 8
            ddq_UB = ddq3_M  # line 9
        else:  # line 10
            ddq_UB = min(ddq1_M, ddq2_M)  # line 11
    else:  # line 12
        ddq_UB = ddq3_M  # line 13
        if ddq3_m < ddq1_M:  # line 14
            ddq_LB = ddq3_m  # line 15
        else:  # line 16
            ddq_LB = max(ddq1_M, ddq2_m)  # line 17
    return ddq_LB, ddq_UB  # line 18


def acc_bounds_from_viability(q, dq, q_min, q_max, ddq_max, dt):
    """Del Prete 2018, Algorithm 2 (accBoundsFromViability), literally. Returns ``(LB, UB)``."""
    a = dt * dt  # line 1
    b = dt * (2.0 * dq + ddq_max * dt)  # line 2
    c = dq * dq - 2.0 * ddq_max * (q_max - q - dt * dq)  # line 3
    ddq_1 = -dq / dt  # line 4
    delta = b * b - 4.0 * a * c  # line 5
    if delta >= 0.0:  # line 6
        ddq_UB = max(ddq_1, (-b + math.sqrt(delta)) / (2.0 * a))  # line 7
    else:  # line 8
        ddq_UB = ddq_1  # line 9
    b = 2.0 * dt * dq - ddq_max * dt * dt  # line 10
    c = dq * dq - 2.0 * ddq_max * (q + dt * dq - q_min)  # line 11
    delta = b * b - 4.0 * a * c  # line 12
    if delta >= 0.0:  # line 13
        ddq_LB = min(ddq_1, (-b - math.sqrt(delta)) / (2.0 * a))  # line 14
    else:  # line 15
        ddq_LB = ddq_1  # line 16
    return ddq_LB, ddq_UB  # line 17


def _paper_viability(q, dq, q_min, q_max, dq_max, ddq_max, dt):
    """Del Prete 2018, Algorithm 3 (Compute Joint Acceleration Bounds), literally."""
    ddq_UB = [0.0, 0.0, 0.0, ddq_max]  # line 1
    ddq_LB = [0.0, 0.0, 0.0, -ddq_max]  # line 2
    ddq_LB[0], ddq_UB[0] = acc_bounds_from_pos_limits(q, dq, q_min, q_max, dt)  # line 3
    ddq_LB[1] = (-dq_max - dq) / dt  # line 4
    ddq_UB[1] = (dq_max - dq) / dt  # line 5
    ddq_LB[2], ddq_UB[2] = acc_bounds_from_viability(q, dq, q_min, q_max, ddq_max, dt)  # line 6
    return max(ddq_LB), min(ddq_UB)  # line 7


def _paper_naive(q, dq, q_min, q_max, dq_max, ddq_max, dt):
    """Del Prete 2018, eq. (2): end-of-step position and velocity limits only."""
    ub = min(ddq_max, (dq_max - dq) / dt, 2.0 / (dt * dt) * (q_max - q - dt * dq))
    lb = max(-ddq_max, (-dq_max - dq) / dt, 2.0 / (dt * dt) * (q_min - q - dt * dq))
    return lb, ub


# ------------------------------------------------------------------ semi-implicit Euler (MuJoCo)


def _semi_end_position_upper(d, v, h, n):
    """Largest ``a`` with ``q_n <= q_max``: ``(d - n h v) / c_n``, ``c_k = h^2 k (k+1) / 2``."""
    return (d - n * h * v) / (h * h * n * (n + 1) / 2.0)


def _semi_position_upper(d, v, h, n):
    """Largest ``a`` with ``q_k <= q_max`` for ``k = 1..n`` (port of ``SemiImplicit.position_upper``)."""
    if v > 0.0 and d >= 0.0:
        k_star = (d + math.sqrt(d * d + h * v * d)) / (h * v)
        k_star = min(max(k_star, 0.0), float(n))
    else:
        k_star = float(n)
    center = math.floor(k_star)
    ks = [min(max(center + off, 1.0), float(n)) for off in (-1.0, 0.0, 1.0, 2.0)] + [1.0, float(n)]
    best = math.inf
    for k in ks:  # the integers around k*, and both ends (a state past the limit, best effort)
        g = (d - k * h * v) / (h * h * k * (k + 1.0) / 2.0)
        if g < best:
            best = g
    return best


def _semi_viability_upper(d, v, a_max, h, n, dt):
    """Largest ``a`` with ``q_n + D(v_n) <= q_max`` (port of ``SemiImplicit.viability_upper``)."""
    R = d - h * (n - 1) * v / 2.0
    rho = max(2.0 * R / (a_max * h * h), 0.0)
    k_hat = math.floor((-n + math.sqrt(float(n * n) + 4.0 * rho)) / 2.0)
    best = math.inf
    for off in (-1.0, 0.0, 1.0):
        K = max(k_hat + off, 0.0)
        x = (2.0 * R / h + a_max * h * K * (K + 1.0)) / (n + 1.0 + 2.0 * K)
        if x < best:
            best = x
    return (best - v) / dt


def semi_implicit_upper(d, v, v_max, a_max, dt, n, method="viability"):
    """Upper-side bound of the semi-implicit model before clipping: ``d = q_max - q`` (or mirrored)."""
    h = dt / n
    ub = min(a_max, (v_max - v) / dt)
    if method == "naive":
        return min(ub, _semi_end_position_upper(d, v, h, n))
    return min(ub, _semi_position_upper(d, v, h, n), _semi_viability_upper(d, v, a_max, h, n, dt))


# ------------------------------------------------------------------ public entry point


def scalar_bounds(q, v, q_min, q_max, v_max, a_max, dt, method="viability", integrator="zoh", substeps=1):
    """``(lower, upper)`` acceleration bounds of one joint for the next control step [rad/s^2].

    ``method="viability"`` with ``integrator="zoh"``: Del Prete's Algorithm 3 (with Alg. 1 and 2).
    ``method="naive"``: eq. (2). ``integrator="semi_implicit"``: the scalar port of jaxlimits'
    semi-implicit formulas with ``substeps`` substeps. Meant for viable states only (see module doc).
    """
    if method not in ("viability", "naive"):
        raise ValueError(f"method must be 'viability' or 'naive', got {method!r}")
    if integrator == "zoh":
        if substeps != 1:
            raise ValueError("substeps applies to integrator='semi_implicit' only")
        fn = _paper_viability if method == "viability" else _paper_naive
        return fn(q, v, q_min, q_max, v_max, a_max, dt)
    if integrator != "semi_implicit":
        raise ValueError(f"integrator must be 'zoh' or 'semi_implicit', got {integrator!r}")
    n = int(substeps)
    upper = semi_implicit_upper(q_max - q, v, v_max, a_max, dt, n, method)
    lower = -semi_implicit_upper(q - q_min, -v, v_max, a_max, dt, n, method)
    return lower, upper
