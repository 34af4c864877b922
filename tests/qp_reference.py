"""An independent exact reference for small box-QPs with halfspaces: active-set enumeration (NumPy).

For ``min 1/2 (x - x_des)^T W (x - x_des)`` s.t. ``lower <= x <= upper``, ``G x <= h`` with SPD
``W`` the optimum is the unique KKT point. Every assignment of each coordinate to {lower, upper,
free} and of each row to {active, inactive} gives an equality-constrained QP; its solution (float64,
one step of iterative refinement) is the optimum iff it is primal feasible and its multipliers have
the right signs. All ``3^n 2^m`` assignments are solved at once and the feasible, dual-feasible one
of least objective is returned (degenerate problems have several assignments with the same ``x``).
Used only by the tests; nothing from ``jaxlimits`` is imported.
"""

from __future__ import annotations

import itertools

import numpy as np


def _assignments(n, m):
    box = np.array(list(itertools.product((0, 1, 2), repeat=n)), dtype=np.int8)  # 0 free, 1 lower, 2 upper
    rows = np.array(list(itertools.product((0, 1), repeat=m)), dtype=bool).reshape(2**m, m)
    B = np.repeat(box, len(rows), axis=0)
    R = np.tile(rows, (len(box), 1))
    return B, R


_CACHE: dict = {}


def least_violation_h(lower, upper, G, h):
    """Rows no box point satisfies are relaxed to their least violation ``min_box G_j x`` (m=1 exact)."""
    gmin = np.sum(np.minimum(G * lower, G * upper), axis=1)
    return np.maximum(h, gmin)


def solve(x_des, lower, upper, W, G=None, h=None, tol=1e-9):
    """The optimum of one problem (float64). Returns ``x``; raises if no assignment is valid."""
    x_des, lower, upper, W = (np.asarray(a, np.float64) for a in (x_des, lower, upper, W))
    n = x_des.shape[0]
    lower = np.broadcast_to(lower, (n,))
    upper = np.broadcast_to(upper, (n,))
    if G is None:
        G = np.zeros((0, n))
        h = np.zeros((0,))
    G, h = np.asarray(G, np.float64), np.asarray(h, np.float64)
    m = G.shape[0]
    key = (n, m)
    if key not in _CACHE:
        _CACHE[key] = _assignments(n, m)
    B, R = _CACHE[key]
    # drop assignments that fix a coordinate of a degenerate box twice
    K = len(B)
    N = n + m
    A = np.zeros((K, N, N))
    rhs = np.zeros((K, N))
    free = B == 0
    fixed_val = np.where(B == 1, lower, upper)
    # stationarity rows (free coords): W x + G^T lam = W x_des ; fixed coords: x_i = bound
    A[:, :n, :n] = np.where(free[:, :, None], W[None], 0.0)
    A[:, :n, n:] = np.where(free[:, :, None], G.T[None], 0.0)
    idx = np.arange(n)
    A[:, idx, idx] = np.where(free, W[idx, idx], 1.0)
    rhs[:, :n] = np.where(free, (W @ x_des)[None], fixed_val)
    # rows: active -> G x = h ; inactive -> lam = 0
    A[:, n:, :n] = np.where(R[:, :, None], G[None], 0.0)
    jdx = np.arange(m)
    A[:, n + jdx, n + jdx] = np.where(R, 0.0, 1.0)
    rhs[:, n:] = np.where(R, h[None], 0.0)
    with np.errstate(all="ignore"):
        sign, _ = np.linalg.slogdet(A)
        ok = sign != 0
        sol = np.full((K, N), np.nan)
        if np.any(ok):
            s = np.linalg.solve(A[ok], rhs[ok][..., None])[..., 0]
            s = s + np.linalg.solve(A[ok], (rhs[ok] - np.einsum("kij,kj->ki", A[ok], s))[..., None])[..., 0]
            sol[ok] = s
    x, lam = sol[:, :n], sol[:, n:]
    scale = 1.0 + np.max(np.abs(x_des)) + np.max(np.abs(np.clip(x_des, lower, upper)))
    gscale = np.max(np.abs(W)) * scale * n
    with np.errstate(invalid="ignore"):
        g = (x - x_des) @ W.T + lam @ G
        primal = np.all((x >= lower - tol * scale) & (x <= upper + tol * scale), axis=1)
        if m:
            primal &= np.all(x @ G.T - h <= tol * (scale * np.max(np.abs(G)) * n + np.abs(h)), axis=1)
            dual = np.all(lam >= -tol * gscale, axis=1)
        else:
            dual = np.ones(K, bool)
        dual &= np.all(np.where(B == 1, g >= -tol * gscale, True) & np.where(B == 2, g <= tol * gscale, True), axis=1)
        f = 0.5 * np.einsum("ki,ij,kj->k", x - x_des, W, x - x_des)
    valid = ok & primal & dual & np.all(np.isfinite(sol), axis=1)
    if not np.any(valid):
        raise RuntimeError("no valid active set (infeasible problem?)")
    best = np.flatnonzero(valid)[np.argmin(f[valid])]
    return np.clip(x[best], lower, upper)


# ------------------------------------------------------------------------------------------------
# infeasible halfspaces: an independent (SciPy) reference of the least-violation definition


def least_violation(lower, upper, G, h):
    """``(r*, x)``: the least violation ``r* = max(G x - h, 0)`` minimising ``||r||`` over the box.

    SciPy's bounded-variable least squares on ``min ||G x - t - h||``, ``lower <= x <= upper``,
    ``t <= 0`` (at the optimum the residual is ``max(G x - h, 0)``).
    """
    from scipy.optimize import lsq_linear

    G, h = np.asarray(G, np.float64), np.asarray(h, np.float64)
    m, n = G.shape
    A = np.concatenate([G, -np.eye(m)], axis=1)
    lb = np.concatenate([np.broadcast_to(lower, (n,)), np.full(m, -np.inf)])
    ub = np.concatenate([np.broadcast_to(upper, (n,)), np.zeros(m)])
    z = lsq_linear(A, h, bounds=(lb, ub), method="bvls", tol=1e-15).x
    return np.maximum(A @ z - h, 0.0), z[:n]


def rows_feasible(lower, upper, G, h):
    """Whether some box point meets every row (SciPy's LP, phase 1)."""
    from scipy.optimize import linprog

    G = np.asarray(G, np.float64)
    n = G.shape[1]
    bounds = list(zip(np.broadcast_to(lower, (n,)), np.broadcast_to(upper, (n,))))
    res = linprog(np.zeros(n), A_ub=G, b_ub=h, bounds=bounds, method="highs")
    return res.status == 0


def solve_least_violation(x_des, lower, upper, W, G, h, slack=1e-11):
    """The documented answer for rows that cannot all hold: ``(x, r*)``.

    ``r*`` from ``least_violation`` (SciPy), then the enumeration ``solve`` on the rows relaxed to
    ``h + r* + slack`` (the slack keeps the thin set of least violation from making every
    active-set system with two of its rows singular; it moves ``x`` by ``O(slack)``).
    """
    G = np.asarray(G, np.float64)
    n = G.shape[1]
    lower, upper = np.broadcast_to(lower, (n,)), np.broadcast_to(upper, (n,))
    r, _ = least_violation(lower, upper, G, h)
    return solve(x_des, lower, upper, W, G, np.asarray(h, np.float64) + r + slack * (1.0 + np.abs(h))), r
