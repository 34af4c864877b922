"""Independent references for the tests: plain-NumPy step simulators and a long-horizon LP.

Nothing here imports jaxlimits' formulas. The LP answers Del Prete's problem (4) directly:
maximise (or minimise) the first acceleration subject to every future limit over a horizon long
enough to come to rest, which is exact for the semi-implicit model (positions at every substep)
and, through cutting planes at each step's position extremum, for the zero-order hold too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog


@dataclass(frozen=True)
class Limits1:
    q_min: float
    q_max: float
    v_max: float
    a_max: float


# ---------------------------------------------------------------- simulators (one joint, numpy)


def zoh_step(q, v, a, T):
    """Exact zero-order-hold step. Returns (q1, v1, q_lo, q_hi): the range of q(t) over [0, T]."""
    q1 = q + T * v + 0.5 * T * T * a
    v1 = v + T * a
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ext = np.where(a != 0, -v / np.where(a != 0, a, 1), -1.0)
    inside = (t_ext > 0) & (t_ext < T)
    q_ext = np.where(inside, q + t_ext * v + 0.5 * t_ext * t_ext * a, q)
    return q1, v1, np.minimum(np.minimum(q, q1), q_ext), np.maximum(np.maximum(q, q1), q_ext)


def semi_implicit_step(q, v, a, T, n, dtype=np.float64):
    """MuJoCo's semi-implicit Euler, n substeps, arithmetic in ``dtype``. Returns (q1, v1, q_lo, q_hi)."""
    q, v, a = (np.asarray(x, dtype) for x in (q, v, a))
    h = dtype(T) / dtype(n)
    q_lo, q_hi = q.copy(), q.copy()
    for _ in range(n):
        v = (v + h * a).astype(dtype)
        q = (q + h * v).astype(dtype)
        q_lo, q_hi = np.minimum(q_lo, q), np.maximum(q_hi, q)
    return q, v, q_lo, q_hi


def zoh_step_dtype(q, v, a, T, dtype=np.float64):
    """The zoh step with its end state rounded as a float ``dtype`` simulator would."""
    q, v, a = (np.asarray(x, dtype) for x in (q, v, a))
    T = dtype(T)
    q1 = (q + T * v + dtype(0.5) * T * T * a).astype(dtype)
    v1 = (v + T * a).astype(dtype)
    _, _, lo, hi = zoh_step(q.astype(np.float64), v.astype(np.float64), a.astype(np.float64), float(T))
    return q1, v1, lo, hi


# ---------------------------------------------------------------- viability by brute force


def brake_peak_semi(v, a_max, h):
    """Peak travel under full braking, simulated substep by substep (semi-implicit)."""
    travel, best = 0.0, 0.0
    while v > 0:
        v -= h * a_max
        travel += h * v
        best = max(best, travel)
    return best


def viable_reference(q, v, lim: Limits1, integrator, T=None, n=1, tol=0.0, curve_margin=0.0):
    """Viability kernel membership by direct simulation of full braking (tolerance ``tol`` on q, v).

    ``curve_margin`` > 0 asks a moving joint to stop at least that far inside the limit, to keep
    sampled states off the exact boundary where rounding decides either way.
    """
    if not (lim.q_min - tol <= q <= lim.q_max + tol and abs(v) <= lim.v_max + tol):
        return False
    if integrator == "zoh":
        up, down = max(v, 0) ** 2 / (2 * lim.a_max), max(-v, 0) ** 2 / (2 * lim.a_max)
    else:
        up, down = brake_peak_semi(v, lim.a_max, T / n), brake_peak_semi(-v, lim.a_max, T / n)
    up_margin = curve_margin if v > 0 else 0.0
    down_margin = curve_margin if v < 0 else 0.0
    return q + up <= lim.q_max + tol - up_margin and q - down >= lim.q_min - tol + down_margin


# ---------------------------------------------------------------- the LP reference


def _affine_rollout(q0, v0, T, H, integrator, n, samples):
    """Rows expressing sampled positions and step-end velocities as affine maps of a (H,)."""
    cq, gq = q0, np.zeros(H)
    cv, gv = v0, np.zeros(H)
    pos_rows, vel_rows = [], []
    for i in range(H):
        e = np.zeros(H)
        e[i] = 1.0
        if integrator == "zoh":
            for t in T * np.arange(1, samples + 1) / samples:
                pos_rows.append((cq + t * cv, gq + t * gv + 0.5 * t * t * e))
            cq, gq = cq + T * cv, gq + T * gv + 0.5 * T * T * e
            cv, gv = cv, gv + T * e
        else:
            h = T / n
            for _ in range(n):
                gv = gv + h * e
                cq, gq = cq + h * cv, gq + h * gv
                pos_rows.append((cq, gq.copy()))
        vel_rows.append((cv, gv.copy()))
    return pos_rows, vel_rows


_HIGHS = {"primal_feasibility_tolerance": 1e-10, "dual_feasibility_tolerance": 1e-10}


def lp_bounds(q0, v0, lim: Limits1, T, integrator="zoh", n=1, horizon=None, samples=8, tol=1e-9, max_rounds=300):
    """(lower, upper) of the first acceleration by LP, or None when the state is not viable.

    Constraints: |a_i| <= a_max; q_min <= q <= q_max at every substep (semi) or at every instant of
    every step (zoh); |v| <= v_max at the start and at every step end; at rest (v = 0) at the end of
    the horizon, from where a = 0 keeps the joint still forever, so a feasible plan is a viable one
    and the optimum is the exact bound of problem (4). For zoh the continuum of position constraints
    is handled by cutting planes: solve with a few samples per step, add a row at each step's true
    extremum t* = -v_i / a_i where the solution exceeds a limit by more than ``tol``, repeat.
    """
    if not (lim.q_min <= q0 <= lim.q_max and abs(v0) <= lim.v_max):
        return None
    if horizon is None:
        horizon = int(math.ceil(2 * lim.v_max / (lim.a_max * T))) + 12
    H = horizon
    pos_rows, vel_rows = _affine_rollout(q0, v0, T, H, integrator, n, samples)
    A_ub, b_ub = [], []
    for c, g in pos_rows:
        A_ub += [g, -g]
        b_ub += [lim.q_max - c, c - lim.q_min]
    for c, g in vel_rows:
        A_ub += [g, -g]
        b_ub += [lim.v_max - c, lim.v_max + c]
    c_end, g_end = vel_rows[-1]
    out = []
    for sign in (1.0, -1.0):
        cost = np.zeros(H)
        cost[0] = sign
        rows, rhs = list(A_ub), list(b_ub)
        for _ in range(max_rounds):
            res = linprog(
                cost,
                A_ub=np.array(rows),
                b_ub=np.array(rhs),
                A_eq=g_end[None],
                b_eq=[-c_end],
                bounds=[(-lim.a_max, lim.a_max)] * H,
                method="highs",
                options=_HIGHS,
            )
            if res.status == 2:
                return None
            assert res.status == 0, res.message
            cuts = _zoh_cuts(res.x, q0, v0, lim, T, tol) if integrator == "zoh" else []
            if not cuts:
                break
            for g, c in cuts:
                rows += [g, -g]
                rhs += [lim.q_max - c, c - lim.q_min]
        else:
            raise AssertionError("cutting planes did not converge")
        out.append(res.x[0])
    return out[0], out[1]


def _zoh_cuts(a, q0, v0, lim, T, tol):
    """Rows (g, c) with q(t*) = c + g @ a at every step whose interior extremum breaks a limit."""
    H = len(a)
    cq, gq, cv, gv = q0, np.zeros(H), v0, np.zeros(H)
    cuts = []
    for i in range(H):
        e = np.zeros(H)
        e[i] = 1.0
        q_i, v_i = cq + gq @ a, cv + gv @ a
        if a[i] != 0:
            t = -v_i / a[i]
            if 0 < t < T:
                q_t = q_i + t * v_i + 0.5 * t * t * a[i]
                if q_t > lim.q_max + tol or q_t < lim.q_min - tol:
                    cuts.append((gq + t * gv + 0.5 * t * t * e, cq + t * cv))
        cq, gq = cq + T * cv, gq + T * gv + 0.5 * T * T * e
        gv = gv + T * e
    return cuts


def certified_safe(q, v, a0, lim: Limits1, T, integrator="zoh", n=1, tol=1e-12, max_steps=2000):
    """A constructive proof that holding ``a0`` now is safe: an explicit plan that never breaks a limit.

    After ``a0``, each step either stops the joint exactly (``a = -v / T``) when that step keeps
    every limit, or brakes fully (``a = -a_max sign(v)``), which may carry it past zero velocity
    and back (the plan that minimises the peak); once at rest, ``a = 0`` keeps it there forever.
    Sufficient, not necessary: it adjudicates the rare states where the LP solver, on a degenerate
    boundary (a single surviving plan), reports a bound tighter than the closed form.
    """

    def step(q, v, a):
        if integrator == "zoh":
            q1, v1, lo, hi = zoh_step(q, v, a, T)
        else:
            q1, v1, lo, hi = semi_implicit_step(q, v, a, T, n)
            q1, v1, lo, hi = float(q1), float(v1), float(lo), float(hi)
        ok = (
            abs(a) <= lim.a_max + tol and lo >= lim.q_min - tol and hi <= lim.q_max + tol and abs(v1) <= lim.v_max + tol
        )
        return ok, float(q1), float(v1)

    ok, q, v = step(q, v, a0)
    if not ok:
        return False
    for _ in range(max_steps):
        if v == 0.0:
            return True
        a_stop = -v / T
        if abs(a_stop) <= lim.a_max:
            ok, q1, v1 = step(q, v, a_stop)
            if ok:
                return True
        ok, q, v = step(q, v, -math.copysign(lim.a_max, v))
        if not ok:
            return False
    return False
