"""Independent references for the jerk-aware bounds: a long-horizon LP and plain-NumPy rollouts.

Nothing here imports jaxlimits' formulas. The LP is ``reference.lp_bounds`` with the previous
acceleration in the state and the jerk rows ``|a_0 - a_prev| <= j_max T``,
``|a_i - a_{i-1}| <= j_max T``; the horizon ends at rest (``v = 0`` *and* ``a = 0``), from where
``a = 0`` keeps the joint still forever without breaking the jerk limit, so a feasible plan is a
viable one and the optimum of ``a_0`` is the exact bound. Zero-order-hold positions inside a step
are bracketed: a relaxation (positions at sample points) and a restriction (the same points kept
``a_max s^2 / 8`` inside, s the sample spacing) bound the exact answer from both sides. (The
cutting planes of ``reference.py`` stall here: with jerk rows the LP's free tail wanders along a
limit and every round finds new ~1e-9 violations.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import linprog

from reference import _HIGHS, _affine_rollout


@dataclass(frozen=True)
class JLimits1:
    q_min: float
    q_max: float
    v_max: float
    a_max: float
    j_max: float


def default_horizon(lim: JLimits1, T: float) -> int:
    """Steps enough to stop from any viable state and recover: stop, ramps and a margin."""
    t = lim.v_max / lim.a_max + 4.0 * lim.a_max / lim.j_max
    return int(math.ceil(t / T)) + 12


def _lp_first(q0, v0, a_prev, lim: JLimits1, T, integrator, n, H, samples, margin):
    """(lower, upper) of a_0 with positions kept ``margin`` inside the limits at the sample points."""
    pos_rows, vel_rows = _affine_rollout(q0, v0, T, H, integrator, n, samples)
    A_ub, b_ub = [], []
    for c, g in pos_rows:
        A_ub += [g, -g]
        b_ub += [lim.q_max - margin - c, c - lim.q_min - margin]
    for c, g in vel_rows:
        A_ub += [g, -g]
        b_ub += [lim.v_max - c, lim.v_max + c]
    dj = lim.j_max * T
    for i in range(H):
        g = np.zeros(H)
        g[i] = 1.0
        if i == 0:
            A_ub += [g, -g]
            b_ub += [dj + a_prev, dj - a_prev]
        else:
            g[i - 1] = -1.0
            A_ub += [g, -g]
            b_ub += [dj, dj]
    c_end, g_end = vel_rows[-1]
    last = np.zeros(H)
    last[-1] = 1.0
    A_ub, b_ub = sparse.csr_matrix(np.array(A_ub)), np.array(b_ub)
    A_eq, b_eq = np.array([g_end, last]), np.array([-c_end, 0.0])
    out = []
    for sign in (1.0, -1.0):
        cost = np.zeros(H)
        cost[0] = sign
        res = linprog(
            cost,
            A_ub=A_ub,
            b_ub=b_ub,
            A_eq=A_eq,
            b_eq=b_eq,
            bounds=[(-lim.a_max, lim.a_max)] * H,
            method="highs",
            options=_HIGHS,
        )
        if res.status == 2:
            return None
        assert res.status == 0, res.message
        out.append(res.x[0])
    return out[0], out[1]


def lp_jerk_bounds(q0, v0, a_prev, lim: JLimits1, T, integrator="zoh", n=1, horizon=None, samples=8):
    """Exact bounds of the first acceleration by LP, bracketed: ``(outer, inner)`` or None.

    ``outer = (lower, upper)`` constrains positions only at ``samples`` points per step (zoh) — a
    relaxation, so its interval contains the exact one; ``inner`` keeps those samples
    ``a_max (T / samples)^2 / 8`` inside the limits, which bounds how far a parabola with
    ``|a| <= a_max`` can rise between samples — a restriction, so its interval is inside the exact
    one (None if that restriction is infeasible). For the semi-implicit model every substep is a
    row and both are the exact answer. Returns None when the relaxation is infeasible: not viable.
    """
    if not (lim.q_min <= q0 <= lim.q_max and abs(v0) <= lim.v_max and abs(a_prev) <= lim.a_max):
        return None
    H = horizon or default_horizon(lim, T)
    outer = _lp_first(q0, v0, a_prev, lim, T, integrator, n, H, samples, 0.0)
    if outer is None or integrator != "zoh":
        return None if outer is None else (outer, outer)
    margin = lim.a_max * (T / samples) ** 2 / 8.0
    inner = _lp_first(q0, v0, a_prev, lim, T, integrator, n, H, samples, margin)
    return outer, inner


def sample_states(lim: JLimits1, count, rng):
    """States concentrated near the limits: position near a limit, moving toward it, any a_prev."""
    span = lim.q_max - lim.q_min
    out = []
    for _ in range(count):
        mode = rng.integers(4)
        u, w, z = rng.uniform(size=3)
        if mode == 0:  # at or very near the limit, slow
            d = span * u**6
            v = lim.v_max * (2 * w - 1) * 0.3
        elif mode == 1:  # near the limit, near the braking curve
            d = span * u**3
            v = math.sqrt(2 * lim.a_max * d) * (0.6 + 0.5 * w)
        elif mode == 2:  # anywhere
            d = span * u
            v = lim.v_max * (2 * w - 1)
        else:  # fast, near the velocity limit
            d = span * u**2
            v = lim.v_max * (1 - 0.2 * w**2)
        v = float(np.clip(v, -lim.v_max, lim.v_max))
        a = lim.a_max * (2 * z - 1)
        if rng.uniform() < 0.5:
            out.append((lim.q_max - d, v, a))
        else:
            out.append((lim.q_min + d, -v, -a))
    return out


# ----------------------------------------------------------------------------- numpy rollouts


def simulate_step(q, v, a, T, integrator, n, dtype=np.float64):
    """(q1, v1, q_lo, q_hi) with the reference simulators of ``reference.py``."""
    from reference import semi_implicit_step, zoh_step, zoh_step_dtype

    if integrator == "zoh":
        return zoh_step_dtype(q, v, a, T, dtype) if dtype != np.float64 else zoh_step(q, v, a, T)
    return semi_implicit_step(q, v, a, T, n, dtype)


# ----------------------------------------------------------------------------- max-braking peak, step by step


def braking_peak_dense(v, a, lim: JLimits1, T, integrator="zoh", n=1):
    """Highest displacement of the max-braking plan ``a_i = max(a - i j_max T, -a_max)``, by simulation.

    Vectorised over the arrays ``v``, ``a`` (float64). Zoh: the highest point of every step's
    parabola after the start (its vertex if the velocity changes sign inside the step, else its
    end). Semi-implicit: every substep. Simulates until every plan is at ``-a_max`` with ``v <= 0``
    (from there the position only falls). Independent of jaxlimits' closed forms.
    """
    v = np.array(v, np.float64)
    a = np.asarray(a, np.float64)
    delta, A, h = lim.j_max * T, lim.a_max, T / n
    p = np.zeros_like(v)
    best = np.full_like(v, -np.inf)
    i = 0
    while True:
        ai = np.maximum(a - i * delta, -A)
        if integrator == "zoh":
            end = p + v * T + 0.5 * ai * T * T
            inside = (v > 0) & (ai < 0) & (v < -ai * T)
            best = np.maximum(best, np.where(inside, p - v * v / (2.0 * np.where(inside, ai, -1.0)), end))
            p, v = end, v + ai * T
        else:
            for _ in range(n):
                v = v + h * ai
                p = p + h * v
                best = np.maximum(best, p)
        i += 1
        if np.all((ai <= -A) & (v <= 0)):
            return best


def position_threshold_dense(d, v, a_prev, lim: JLimits1, T, integrator="zoh", n=1, iterations=48):
    """Largest ``a`` in the jerk box ``[lo, hi]`` with ``braking_peak_dense(v, a) <= d``, by bisection.

    ``hi`` also respects the velocity limit (brute force over the plan's velocities). Returns
    ``(threshold, lo, hi)``; ``hi`` where it passes, ``lo`` where nothing passes (as ``jerk.py``).
    """
    d, v, a_prev = (np.asarray(x, np.float64) for x in (d, v, a_prev))
    delta, A = lim.j_max * T, lim.a_max
    lo = np.maximum(np.clip(a_prev, -A, A) - delta, -A)
    hi = np.minimum(np.clip(a_prev, -A, A) + delta, A)
    # velocity: v + T sum_{i<K} (a - i delta) <= v_max for every K, i.e. a <= min_K (...)/K
    K = np.arange(1, int(np.ceil(2 * (lim.v_max + A * T) / (delta * T))) + 3, dtype=np.float64)[:, None]
    v_thr = np.min(((lim.v_max - v) / T + delta * K * (K - 1) / 2) / K, axis=0)
    hi = np.maximum(np.minimum(hi, v_thr), lo)
    ok = lambda x: braking_peak_dense(v, x, lim, T, integrator, n) <= d  # noqa: E731
    good, bad = lo.copy(), hi.copy()
    for _ in range(iterations):
        mid = 0.5 * (good + bad)
        p = ok(mid)
        good, bad = np.where(p, mid, good), np.where(p, bad, mid)
    return np.where(ok(hi), hi, good), lo, hi


# ------------------------------------------------------------------------- exact first step, restricted first command


def first_step_interval(q0, v0, lim: JLimits1, T):
    """The exact zoh interval of ``a_0`` keeping the first step's parabola ``q0 + v0 t + a_0 t^2 / 2`` inside.

    Upper side: ``a_0 <= min_{0 < t <= T} 2 (d - v0 t) / t^2`` (``d = q_max - q0``), the minimum at
    ``t* = 2 d / v0`` (value ``-v0^2 / (2 d)``) when ``v0 > 0`` and ``t* <= T``, else at ``t = T``;
    lower side the mirror image. The first step is fixed by ``a_0`` alone, so this is necessary for
    every plan; the sampled rows miss it when the step's extremum is before the first sample (a
    state just under a limit, nearly at rest).
    """

    def upper(d, v):
        if v > 0 and 2 * d <= v * T:
            return -v * v / (2 * d) if d > 0 else -math.inf
        return 2 * (d - v * T) / (T * T)

    return -upper(q0 - lim.q_min, -v0), upper(lim.q_max - q0, v0)


def _jerk_lp(q0, v0, a_prev, lim: JLimits1, T, integrator, n, H, samples, margin, first, objective):
    """One LP of ``lp_jerk_bounds``' rows: ``objective`` in ``(None, +1, -1)`` (feasibility, min a_0, max a_0).

    ``first``: extra bounds on ``a_0``; with it, zoh position rows of step 0 carry no ``margin``
    (the interval is exact there). Returns the optimal ``a_0`` (``0.0`` for feasibility) or None.
    """
    pos_rows, vel_rows = _affine_rollout(q0, v0, T, H, integrator, n, samples)
    A_ub, b_ub = [], []
    for k, (c, g) in enumerate(pos_rows):
        m = 0.0 if (first is not None and integrator == "zoh" and k < samples) else margin
        A_ub += [g, -g]
        b_ub += [lim.q_max - m - c, c - lim.q_min - m]
    for c, g in vel_rows:
        A_ub += [g, -g]
        b_ub += [lim.v_max - c, lim.v_max + c]
    dj = lim.j_max * T
    for i in range(H):
        g = np.zeros(H)
        g[i] = 1.0
        if i == 0:
            A_ub += [g, -g]
            b_ub += [dj + a_prev, dj - a_prev]
        else:
            g[i - 1] = -1.0
            A_ub += [g, -g]
            b_ub += [dj, dj]
    c_end, g_end = vel_rows[-1]
    last = np.zeros(H)
    last[-1] = 1.0
    bounds = [(-lim.a_max, lim.a_max)] * H
    if first is not None:
        bounds[0] = (max(first[0], -lim.a_max), min(first[1], lim.a_max))
        if bounds[0][0] > bounds[0][1]:
            return None
    cost = np.zeros(H)
    cost[0] = objective or 0.0
    res = linprog(
        cost,
        A_ub=sparse.csr_matrix(np.array(A_ub)),
        b_ub=np.array(b_ub),
        A_eq=np.array([g_end, last]),
        b_eq=np.array([-c_end, 0.0]),
        bounds=bounds,
        method="highs",
        options=_HIGHS,
    )
    if res.status == 2:
        return None
    assert res.status == 0, res.message
    return 0.0 if objective is None else float(res.x[0])


def lp_jerk_bounds_exact_first(q0, v0, a_prev, lim: JLimits1, T, integrator="zoh", n=1, horizon=None, samples=8):
    """``lp_jerk_bounds`` with the zoh first step exact (``first_step_interval``): a valid bracket near a limit too.

    ``lp_jerk_bounds``' restriction keeps the samples ``a_max s^2 / 8`` inside, which bounds the
    parabola between two samples, but not between the start ``q0`` (not kept inside) and the first
    sample: for a state just under a limit and nearly at rest the step-0 peak lies there, and its
    "inner" interval is not inside the exact one. Here step 0 is the exact interval of ``a_0`` (no
    sampled rows with margin), later steps as before, so ``(outer, inner)`` bracket the exact bounds
    for every state (semi-implicit: exact, as before). None: not viable.
    """
    if not (lim.q_min <= q0 <= lim.q_max and abs(v0) <= lim.v_max and abs(a_prev) <= lim.a_max):
        return None
    H = horizon or default_horizon(lim, T)
    first = first_step_interval(q0, v0, lim, T) if integrator == "zoh" else None
    out = []
    for margin in (0.0, lim.a_max * (T / samples) ** 2 / 8.0) if integrator == "zoh" else (0.0,):
        pair = [_jerk_lp(q0, v0, a_prev, lim, T, integrator, n, H, samples, margin, first, s) for s in (1.0, -1.0)]
        out.append(None if None in pair else tuple(pair))
    if out[0] is None:
        return None
    return out[0], (out[-1] if integrator == "zoh" else out[0])


def lp_jerk_feasible(q0, v0, a_prev, lim: JLimits1, T, integrator="zoh", n=1, horizon=None, samples=8, first=None):
    """Whether the LP *relaxation* of ``lp_jerk_bounds`` has a plan whose first command lies in ``first``.

    ``first = (lo, hi)`` restricts ``a_0`` (default: the whole ``[-a_max, a_max]``). Positions are
    rows at ``samples`` points per step (zoh; every substep for the semi-implicit model, exact), so
    ``False`` proves that no admissible plan starts with such an ``a_0`` (the relaxation is
    infeasible), and with ``first`` a *necessary* condition on ``a_0`` (e.g. ``first_step_interval``,
    or a bound from the first step alone, which ``a_0`` fixes for every plan) it proves the state is
    not viable. Same rows as ``lp_jerk_bounds``: jerk, velocity at every step end, rest (``v = 0``,
    ``a = 0``) at the horizon.
    """
    if not (lim.q_min <= q0 <= lim.q_max and abs(v0) <= lim.v_max and abs(a_prev) <= lim.a_max):
        return False
    H = horizon or default_horizon(lim, T)
    return _jerk_lp(q0, v0, a_prev, lim, T, integrator, n, H, samples, 0.0, first, None) is not None
