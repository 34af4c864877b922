"""The differentiable box-QP projection (with optional halfspaces); see ``docs/qp.md``.

Solves, per problem of a batch,

    min_x  1/2 (x - x_des)^T W (x - x_des)   s.t.   lower <= x <= upper,   G x <= h.

* ``metric=None`` or a 1-D positive diagonal, no halfspaces: the exact clip, with a custom JVP
  (identity on free coordinates, zero on active ones; the tie rule is in ``_clip``).
* dense SPD metric and/or halfspaces (``_dense_batched``), three stages, none differentiated:
  1. the fast path (``qp_pdas``): block principal pivoting, the whole batch at once (row form for
     ``n <= UNROLL_MAX``), every iteration an exact solve of the current active set; it stops
     once only a few problems of the batch are left unsettled;
  2. the robust path for those (``_fallback``, gathered ``chunk`` at a time): for ``m >= 2`` the
     least violation of the rows first (``qp_bvls``), then the primal active-set method
     (``_active_set_solve``) from a feasible point, on the set of least violation;
  3. the implicit derivative attached to the solution (``_attach``, a ``jax.custom_jvp``): the KKT
     system of the final active set of the problem actually solved (forward and reverse mode).
* The returned ``x`` is always clipped to the box at the end: the box holds exactly whatever the
  iteration count did.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits._src import qp_bvls, qp_pdas
from jaxlimits._src.qp_checks import check_inputs
from jaxlimits._src.qp_linalg import UNROLL_MAX, chol_apply, chol_factor, chol_solve, masked_matrix, rdot, rmatvec, rmatvec_t

GRADIENTS = ("exact", "straight_through")


class BoxQPResult(NamedTuple):
    """Result of ``solve_box_qp``; every field is batched like ``x_des`` without its last axis.

    x: ``(..., n)``, the projection; ``lower <= x <= upper`` holds exactly, always.
    converged: ``(...)`` bool, the KKT conditions hold to the solver tolerance (always True for
      the clip).
    iterations: ``(...)`` int32, active-set iterations spent (0 for the clip).
    infeasible: ``(...)`` bool, the halfspaces cannot all hold together with the box; they are
      met with the least violation (see ``solve_box_qp``). False without halfspaces.
    violation: ``(...)`` ``max_j max(0, G_j x - h_j)`` of the returned ``x`` (0 without halfspaces).
    """

    x: jax.Array
    converged: jax.Array
    iterations: jax.Array
    infeasible: jax.Array
    violation: jax.Array


# --------------------------------------------------------------------------------------------
# the clip (metric None or diagonal, no halfspaces)


@jax.custom_jvp
def _clip(x_des, lower, upper):
    return jnp.minimum(jnp.maximum(x_des, lower), upper)


@_clip.defjvp
def _clip_jvp(primals, tangents):
    """The true derivative, with ties decided on purpose.

    A coordinate is free (derivative 1 w.r.t. ``x_des``) when ``lower <= x_des <= upper`` and
    ``lower < upper``: at a tie ``x_des == bound`` the derivative is the one from inside the box.
    Otherwise it follows the bound it sits on (``lower`` when ``x_des <= lower``, else ``upper``),
    so a degenerate box ``lower == upper`` passes no gradient to ``x_des``. (``jnp.clip`` would
    give 1/2 at a tie.)
    """
    x_des, lower, upper = primals
    dx, dl, du = tangents
    x = _clip(x_des, lower, upper)
    free = (x_des >= lower) & (x_des <= upper) & (lower < upper)
    at_lower = x_des <= lower
    return x, jnp.where(free, dx, jnp.where(at_lower, dl, du))


# --------------------------------------------------------------------------------------------
# dense metric and halfspaces: one problem (vmapped by the caller)


def _scales(x_des, lower, upper, W, G, h):
    """Absolute tolerances in units of x, of the gradient and of the halfspace rows."""
    eps = jnp.finfo(x_des.dtype).eps
    sx = 1.0 + jnp.max(jnp.abs(jnp.clip(x_des, lower, upper))) + jnp.max(jnp.abs(x_des - jnp.clip(x_des, lower, upper)))
    sw = jnp.max(jnp.abs(W))
    n = x_des.shape[-1]
    tol_x = 32.0 * eps * sx
    tol_g = 4.0 * eps * sw * sx * n
    gnorm = jnp.max(jnp.abs(G), axis=-1) if G.shape[0] else jnp.zeros((0,), x_des.dtype)
    tol_h = 32.0 * eps * (gnorm * sx * n + jnp.abs(h))
    return tol_x, tol_g, tol_h


def _kkt_solve(W, G, free, rows, r, s, unroll=True):
    """Solve the equality-constrained KKT system of an active set.

    Unknowns ``y`` (on ``free`` coordinates; 0 elsewhere) and ``lam`` (on active ``rows``; 0
    elsewhere) with ``W_FF y_F + G_RF^T lam_R = r_F`` and ``G_RF y_F = s_R`` (Schur complement on
    the small ``m x m`` block, regularised by a few ulps so that dependent rows stay finite, plus
    one refinement step).
    """
    n, m = W.shape[0], G.shape[0]
    M = masked_matrix(W, free)
    rf = jnp.where(free, r, 0.0)
    if m == 0:
        return jnp.where(free, chol_solve(M, rf, unroll), 0.0), jnp.zeros((0,), W.dtype)
    GF = jnp.where(free[None, :], G, 0.0)
    eps = jnp.finfo(W.dtype).eps
    # a row whose free part vanishes is fixed by the box alone: nothing to solve for it
    rows = rows & (jnp.sum(GF * GF, axis=1) > eps * eps * jnp.sum(G * G, axis=1))
    GF = jnp.where(rows[:, None], GF, 0.0)
    fac = chol_factor(M, unroll)
    y, Z = chol_apply(fac, rf), chol_apply(fac, GF.T)  # apart: y is linear in tangents, Z is not
    S = GF @ Z
    reg = 1e2 * eps * (jnp.max(jnp.abs(jnp.diagonal(S))) + jnp.finfo(W.dtype).tiny)
    S = masked_matrix(S, rows) + reg * jnp.eye(m, dtype=W.dtype)
    Sf = chol_factor(S, unroll)
    lam = jnp.where(rows, chol_apply(Sf, jnp.where(rows, GF @ y - s, 0.0)), 0.0)
    # one step of iterative refinement on the rows: undoes the regularisation where the held rows
    # are nearly dependent (large multipliers), so that they hold to rounding
    e = jnp.where(rows, GF @ (y - Z @ lam) - s, 0.0)
    lam = lam + jnp.where(rows, chol_apply(Sf, e), 0.0)
    x = jnp.where(free, y - Z @ lam, 0.0)
    return x, lam


def _active_sets(x, x_des, lower, upper, W, G, lam, tol_g):
    """Box coordinates held by a strictly positive multiplier (ties count as free)."""
    g = W @ (x - x_des) + G.T @ lam
    hold_l = (x <= lower) & (g > tol_g)
    hold_u = (x >= upper) & (g < -tol_g)
    free = ~(hold_l | hold_u) & (lower < upper)
    return free, g


def _kkt_ok(x, x_des, lower, upper, W, G, h, lam, tols, eq):
    """The KKT conditions hold at ``(x, lam)`` to 30 times the tolerances ``tols`` (rounding).

    Rows in ``eq`` are equalities (multiplier of either sign).
    """
    tol_x, tol_g, tol_h = (30.0 * t for t in tols)
    g = W @ (x - x_des) + G.T @ lam
    inside = jnp.all((x >= lower - tol_x) & (x <= upper + tol_x))
    at_l = x <= lower + tol_x
    at_u = x >= upper - tol_x
    fixed = lower >= upper
    stat = jnp.all(fixed | (at_l & (g >= -tol_g)) | (at_u & (g <= tol_g)) | (jnp.abs(g) <= tol_g))
    if G.shape[0] == 0:
        return inside & stat
    gx = G @ x - h
    primal_h = jnp.all(jnp.where(eq, jnp.abs(gx), gx) <= tol_h)
    dual_h = jnp.all(eq | (lam >= 0.0)) & jnp.all(eq | (lam == 0.0) | (jnp.abs(gx) <= tol_h))
    return inside & stat & primal_h & dual_h


def _feasible_start(y, lower, upper, G, h, passes: int = 2):
    """A box point meeting the rows, from ``y``: move towards the face minimising each violated row.

    The face ``argmin_box G_j x`` meets row ``j`` (rows that cannot were relaxed beforehand), and
    ``y + beta (face - y)`` with ``beta = (G_j y - h_j) / (G_j y - G_j face)`` meets it with
    equality inside the box. Exact for one row (the only use: ``m >= 2`` starts from the least
    violation point of ``qp_bvls``).
    """
    for _ in range(passes):
        for j in range(G.shape[0]):
            g = G[j]
            face = jnp.where(g > 0, lower, jnp.where(g < 0, upper, y))
            over = g @ y - h[j]
            drop = g @ y - g @ face
            beta = jnp.where((over > 0) & (drop > 0), over / jnp.where(drop > 0, drop, 1.0), 0.0)
            y = jnp.clip(y + jnp.clip(beta, 0.0, 1.0) * (face - y), lower, upper)
    return y


def _dependent(G, free, rows, unroll=True):
    """Candidates of the working set already in the span of its held rows (on the free coordinates).

    The candidates are the box bounds of each coordinate (the unit vectors, first ``n``) and the
    rows (last ``m``): ``(n + m,)`` bool, True where the part of the candidate on ``free`` is, to
    ``1e3 eps`` of its norm, a combination of the free parts of the ``rows`` held. Such a
    constraint cannot block a step of the working set in exact arithmetic (the step keeps the held
    rows, hence it, unchanged); letting it join on rounding makes the working set dependent, and
    the active-set method can then cycle (a duplicate row released and re-added forever).
    """
    n, m = G.shape[1], G.shape[0]
    eps = jnp.finfo(G.dtype).eps
    V = jnp.concatenate([jnp.eye(n, dtype=G.dtype), G], axis=0)
    VF = jnp.where(free[None, :], V, 0.0)
    A = jnp.where(rows[:, None] & free[None, :], G, 0.0)
    S = A @ A.T
    reg = 1e2 * eps * (jnp.max(jnp.abs(jnp.diagonal(S))) + jnp.finfo(G.dtype).tiny)
    S0 = masked_matrix(S, rows)
    fac = chol_factor(S0 + reg * jnp.eye(m, dtype=G.dtype), unroll)
    B = jnp.where(rows[:, None], A @ VF.T, 0.0)
    C = jnp.where(rows[:, None], chol_apply(fac, B), 0.0)
    # one refinement step: removes the regularisation's error (relative reg * cond(S) otherwise)
    C = C + jnp.where(rows[:, None], chol_apply(fac, B - S0 @ C), 0.0)
    R = VF - C.T @ A
    tol = 1e3 * eps
    return jnp.sum(R * R, axis=1) <= tol * tol * jnp.sum(V * V, axis=1)


def _independent_rows(G, free, cand, eq):
    """A working set of rows: every ``eq`` row, then the ``cand`` rows (in index order) whose free
    part is independent of those already taken (Gram-Schmidt on the free coordinates, ``1e3 eps``)."""
    m = G.shape[0]
    eps = jnp.finfo(G.dtype).eps
    GF = jnp.where(free[None, :], G, 0.0)
    basis = []
    take = [None] * m
    for phase in (0, 1):
        for j in range(m):
            v = GF[j]
            for q in basis:
                v = v - (q @ v) * q
            nv2 = v @ v
            indep = nv2 > (1e3 * eps) ** 2 * (G[j] @ G[j])
            if phase == 0:
                take[j] = eq[j]
            else:
                take[j] = eq[j] | (cand[j] & indep)
            use = (eq[j] if phase == 0 else (~eq[j] & take[j])) & indep
            basis.append(jnp.where(use, v / jnp.sqrt(jnp.where(indep, nv2, 1.0)), 0.0))
    return jnp.stack(take)


def _active_set_solve(x_des, lower, upper, W, G, h, eq, start, max_iter, tols):
    """Primal active-set method on the box and the rows (working set: held bounds and rows).

    The robust path, for the problems the fast path (``qp_pdas``) did not settle. Each iteration
    solves the equality-constrained QP of the working set exactly (``_kkt_solve``) and steps towards
    its solution ``z``: all the way if no constraint outside the working set blocks (then the
    multiplier of most negative sign, if any, is released), else up to the first blocking
    constraint, which joins the working set. The working set stays linearly independent: a
    constraint dependent on the held rows never blocks (``_dependent``), else exact duplicate rows
    cycle on rounding (a copy joins at a zero step, gets a negative multiplier, leaves, joins...).
    From a feasible point the objective never increases and no working set repeats, so it
    terminates (finitely, in exact arithmetic). ``start`` is a box point (meeting the rows, or
    violating held ones: they hold with equality after the first full step); the bounds it sits on
    and the rows it meets with equality (those independent of the ones taken before them,
    ``_independent_rows``) start in the working set. Rows in ``eq`` are equalities: always held,
    never released.
    """
    tol_x, tol_g, tol_h = tols
    n, m = W.shape[0], G.shape[0]
    flat = lower >= upper
    y0 = start
    held_l0 = (y0 <= lower) | flat
    held_u0 = (y0 >= upper) & ~held_l0
    # the rows met with equality at the start, but no row dependent on those taken (anti-cycling)
    rows0 = _independent_rows(G, ~(held_l0 | held_u0), G @ y0 - h >= -tol_h, eq) if m else jnp.zeros((0,), bool)
    wdx = W @ x_des
    wd = jnp.sqrt(jnp.abs(jnp.diagonal(W))) + jnp.finfo(W.dtype).tiny
    gn = jnp.sqrt(jnp.sum(G * G, axis=1)) + jnp.finfo(W.dtype).tiny
    idx = jnp.arange(2 * n + m)

    def body(state):
        y, hl, hu, rows, lam, it, _ = state
        free = ~(hl | hu)
        xa = jnp.where(hl, lower, jnp.where(hu, upper, 0.0))
        zf, lam_z = _kkt_solve(W, G, free, rows, wdx - W @ xa, h - G @ xa)
        z = zf + xa
        d = jnp.where(free, z - y, 0.0)
        # blocking box bounds (free coordinates only) and rows outside the working set; a constraint
        # dependent on the held rows never blocks (anti-cycling: the working set stays independent)
        dep = _dependent(G, free, rows, unroll=False) if m else jnp.zeros((n,), bool)
        free_b = free & ~dep[:n]
        ratio_l = jnp.where(free_b & (d < 0), (lower - y) / jnp.where(d < 0, d, -1.0), jnp.inf)
        ratio_u = jnp.where(free_b & (d > 0), (upper - y) / jnp.where(d > 0, d, 1.0), jnp.inf)
        ratios = [ratio_l, ratio_u]
        if m:
            gd = G @ d
            slack = jnp.maximum(h - G @ y, 0.0)
            ratios.append(jnp.where(~rows & ~dep[n:] & (gd > 0), slack / jnp.where(gd > 0, gd, 1.0), jnp.inf))
        allr = jnp.concatenate(ratios)
        k = jnp.argmin(allr)
        blocked = allr[k] < 1.0
        a = jnp.clip(allr[k], 0.0, 1.0)
        add = blocked & (idx == k)
        add_l, add_u = add[:n], add[n:2 * n]
        y_step = jnp.where(free, jnp.clip(y + a * d, lower, upper), y)
        y_full = jnp.where(free, jnp.clip(z, lower, upper), y)
        y_new = jnp.where(add_l, lower, jnp.where(add_u, upper, jnp.where(blocked, y_step, y_full)))
        hl2, hu2 = hl | add_l, hu | add_u
        rows2 = rows | add[2 * n:]
        # at the working-set optimum: release the most negative (scaled) multiplier, or stop
        g = W @ (y_new - x_des) + G.T @ lam_z
        mult = jnp.where(hl & ~flat, g / wd, jnp.where(hu, -g / wd, jnp.inf))
        cand = jnp.concatenate([mult, jnp.full((n,), jnp.inf, W.dtype), jnp.where(rows & ~eq, lam_z * gn, jnp.inf)])
        j = jnp.argmin(cand)
        neg = cand[j] < -tol_g / jnp.max(wd)
        release = ~blocked & neg & (idx == j)
        hl2 = hl2 & ~release[:n]
        hu2 = hu2 & ~release[:n]
        rows2 = rows2 & ~release[2 * n:]
        done = ~blocked & ~neg
        lam_new = jnp.where(rows2, lam_z, 0.0)
        return y_new, hl2, hu2, rows2, lam_new, it + 1, done

    def cond(state):
        return (state[5] < max_iter) & ~state[6]

    init = (y0, held_l0, held_u0, rows0, jnp.zeros((m,), W.dtype), jnp.int32(0), jnp.bool_(False))
    y, _, _, _, lam, it, done = jax.lax.while_loop(cond, body, init)
    return y, lam, done, it


def _pin_infeasible_rows(lower, upper, G, h):
    """Rows that no box point satisfies: pin their coordinates at the minimising bounds, drop them.

    ``min_{lower<=x<=upper} G_j x = sum_i min(G_ji lower_i, G_ji upper_i)`` is attained exactly on
    the face ``x_i = lower_i`` (``G_ji > 0``), ``x_i = upper_i`` (``G_ji < 0``); if it is ``>= h_j``
    that face is the set of least violation of row ``j`` (exactly its feasible set at equality).
    Used for ``m == 1`` (closed form); ``m >= 2`` goes through ``qp_bvls``.
    """
    gmin = jnp.sum(jnp.minimum(G * lower[None, :], G * upper[None, :]), axis=1)
    pin_row = gmin >= h
    infeasible = jnp.any(gmin > h)
    pin_l = jnp.any(pin_row[:, None] & (G > 0), axis=0)
    pin_u = jnp.any(pin_row[:, None] & (G < 0), axis=0) & ~pin_l
    lo = jnp.where(pin_u, upper, lower)
    hi = jnp.where(pin_l, lower, upper)
    G2 = jnp.where(pin_row[:, None], 0.0, G)
    h2 = jnp.where(pin_row, 0.0, h)
    return lo, hi, G2, h2, infeasible


def _least_violation_split(lower, upper, G, h, r, relax, tols):
    """The problem on the set of least violation ``{box, G x <= h + r}`` (discrete decisions only).

    On that set every row with ``r_j > 0`` holds with equality and every coordinate with
    ``q_i = (G^T r)_i != 0`` sits at the bound minimising ``q_i x_i`` (phase-1 optimality), so:
    pin those coordinates; pin the face of any row that is tight on the (pinned) box
    (``min_box G_j x >= h_j + r_j``) and drop it; drop rows with no free coordinate left; the
    relaxed rows are then dependent (``sum_j r_j G_jF = 0``): drop the one with the largest
    ``r_j``, hold the others as equalities. Returns ``(pin_l, pin_u, drop, eq)``.
    """
    n, m = G.shape[1], G.shape[0]
    eps = jnp.finfo(G.dtype).eps
    _, _, tol_h = tols
    r = jnp.where(relax, r, 0.0)
    he = h + r
    q = G.T @ r
    tol_q = 1e3 * eps * n * m * (jnp.max(jnp.abs(G)) * jnp.max(r) + jnp.finfo(G.dtype).tiny)
    pin_l = q > tol_q
    pin_u = q < -tol_q
    lo1 = jnp.where(pin_u, upper, lower)
    hi1 = jnp.where(pin_l, lower, upper)
    gmin = jnp.sum(jnp.minimum(G * lo1[None, :], G * hi1[None, :]), axis=1)
    tight = gmin >= he - 30.0 * tol_h
    pl2 = jnp.any(tight[:, None] & (G > 0), axis=0)
    pu2 = jnp.any(tight[:, None] & (G < 0), axis=0) & ~pl2
    pin_l = pin_l | (~pin_u & pl2)
    pin_u = pin_u | (~pin_l & pu2)
    pinned = pin_l | pin_u | (lower >= upper)
    GF = jnp.where(pinned[None, :], 0.0, G)
    drop = tight | (jnp.sum(GF * GF, axis=1) <= eps * eps * jnp.sum(G * G, axis=1))
    J = relax & (r > 30.0 * tol_h) & ~drop
    j0 = jnp.argmax(jnp.where(J, r, -1.0))
    drop0 = J & (jnp.arange(m) == j0) & (jnp.sum(J) >= 2)
    return pin_l, pin_u, drop | drop0, J & ~drop0


def _fallback_one(x_des, lower, upper, W, G, h, x_warm, max_iter):
    """The robust path for one problem: ``(x, lam, ok, it, relax, zfree, zup, pin_l, pin_u, drop, eq)``.

    ``m >= 2``: the least violation ``r*`` first (``qp_bvls``); ``relax`` when some row cannot
    hold (``r* > 0``), then the problem is solved on the set of least violation
    (``_least_violation_split``) from the BVLS point. The returned split describes the problem
    actually solved, for the derivative.
    """
    n, m = W.shape[0], G.shape[0]
    W = 0.5 * (W + W.T)
    tols = _scales(x_des, lower, upper, W, G, h)
    nob = jnp.zeros((n,), bool)
    zfree = jnp.zeros((n + m,), bool) if m >= 2 else jnp.zeros((0,), bool)
    zup = zfree
    relax = jnp.bool_(False)
    pin_l, pin_u, drop, eq = nob, nob, jnp.zeros((m,), bool), jnp.zeros((m,), bool)
    lo, hi, Ge, he = lower, upper, G, h
    lv_ok = jnp.bool_(True)
    rr = jnp.zeros((m,), W.dtype)
    if m >= 2:
        zfree, zup, zb, _ = qp_bvls.bvls(lower, upper, G, h, 4 * (n + m) + 10)
        r, _ = qp_bvls.residual(lower, upper, G, h, zfree, zup)
        xbar = zb[:n]
        # infeasible only with a certificate: gap > 0 is impossible if some box point meets every
        # row (a residual r of mere rounding never passes it)
        gap, err = qp_bvls.certificate(lower, upper, G, h, r)
        relax = jnp.any(r > 30.0 * tols[2]) & (gap > 16.0 * err)
        rr = jnp.where(relax, r, 0.0)
        # r is the least violation to rounding: ||r||^2 - gap = sum_i |q_i| dist(x_i, its bound)
        # at the BVLS point, rounding-level where q_i ~ 0 (q_i's rounding: the rows' own scales)
        s = qp_bvls.row_scale(lower, upper, G, h)
        eps = jnp.finfo(W.dtype).eps
        lv_tol = 1e3 * (err + eps * (n + m) * jnp.sum(jnp.where(r > 0, s * s, 0.0)))
        lv_ok = ~relax | (r @ r - gap <= lv_tol)
        pin_l, pin_u, drop, eq = _least_violation_split(lower, upper, G, h, r, relax, tols)
        lo = jnp.where(pin_u, upper, lower)
        hi = jnp.where(pin_l, lower, upper)
        Ge = jnp.where(drop[:, None], 0.0, G)
        he = jnp.where(drop, 0.0, h + rr)
        start = jnp.clip(xbar, lo, hi)
    elif m == 1:
        start = _feasible_start(jnp.clip(x_warm, lower, upper), lower, upper, G, h)
    else:
        start = jnp.clip(x_warm, lower, upper)
    tols = _scales(x_des, lo, hi, W, Ge, he)
    x, lam, done, it = _active_set_solve(x_des, lo, hi, W, Ge, he, eq, start, max_iter, tols)
    x = jnp.clip(x, lo, hi)
    ok = done & _kkt_ok(x, x_des, lo, hi, W, Ge, he, lam, tols, eq) & lv_ok
    if m:  # every row as given (dropped and pinned ones too) holds at x, relaxed by r* if infeasible
        tol_h = _scales(x_des, lower, upper, W, G, h + rr)[2]
        slack = 30.0 * tol_h + 32.0 * jnp.finfo(W.dtype).eps * (jnp.abs(G) @ jnp.abs(x))
        ok = ok & jnp.all(G @ x - (h + rr) <= slack)
    return x, lam, ok, it, relax, zfree, zup, pin_l, pin_u, drop, eq


def _fallback(args, x, lam, ok, it, max_iter, chunk):
    """Run ``_fallback_one`` on the problems not ``ok``, ``chunk`` at a time (gathered in and out).

    Returns ``(x, lam, ok, it, split)`` for the whole batch; ``split`` (``relax, zfree, zup, pin_l,
    pin_u, drop, eq``) is False for the problems the fast path settled.
    """
    B = x.shape[0]
    n, m = x.shape[1], lam.shape[1]
    nz = n + m if m >= 2 else 0
    split0 = (jnp.zeros((B,), bool), jnp.zeros((B, nz), bool), jnp.zeros((B, nz), bool), jnp.zeros((B, n), bool),
              jnp.zeros((B, n), bool), jnp.zeros((B, m), bool), jnp.zeros((B, m), bool))
    out0 = (x, lam, ok, it) + split0

    def body(state):
        out, pending = state
        # the first ``chunk`` pending problems: gathered in, and gathered back by position (no
        # scatter: scatters compile slowly on the CPU)
        idx = jnp.nonzero(pending, size=chunk, fill_value=B - 1)[0]
        pos = jnp.cumsum(pending.astype(jnp.int32)) - 1
        take = pending & (pos < chunk)
        pos = jnp.clip(pos, 0, chunk - 1)
        sub = [a[idx] for a in args] + [out[0][idx]]
        res = jax.vmap(lambda *a: _fallback_one(*a, max_iter))(*sub)
        res = (res[0], res[1], res[2], res[3] + out[3][idx]) + tuple(res[4:])

        def back(o, r):
            t = take.reshape((B,) + (1,) * (o.ndim - 1))
            return jnp.where(t, r[pos], o)

        out = tuple(back(o, r) for o, r in zip(out, res))
        return out, pending & ~take

    out, _ = jax.lax.while_loop(lambda s: jnp.any(s[1]), body, (out0, ~ok))
    return out[0], out[1], out[2], out[3], out[4:]


# --------------------------------------------------------------------------------------------
# the derivative: implicit, attached to the solution of the problem actually solved


def _tangent(x, lam, primals, tangents, tol_g, eq):
    """Implicit derivative (array form, one problem): the KKT conditions of the final active set."""
    x_des, lower, upper, W, G, h = primals
    dxd, dl, du, dW, dG, dh = tangents
    free, _ = _active_sets(x, x_des, lower, upper, W, G, lam, tol_g)
    at_l = x <= 0.5 * (lower + upper)
    dxa = jnp.where(free, 0.0, jnp.where(at_l, dl, du))
    r = W @ dxd - dW @ (x - x_des) - dG.T @ lam - W @ dxa
    rows = (lam > 0) | eq
    s = dh - dG @ x - G @ dxa
    dxf, _ = _kkt_solve(W, G, free, rows, r, s)
    return dxf + dxa


def _tangent_rows(x, lam, primals, tangents, eq):
    """``_tangent`` in row form (every argument a list of rows; ``W``, ``G``, ``dW``, ``dG`` nested)."""
    x_des, lower, upper, W, G, h = primals
    dxd, dl, du, dW, dG, dh = tangents
    n, m = len(x), len(lam)
    _, tol_g, _ = qp_pdas.scales_rows(x_des, lower, upper, W, G, h)
    g = rmatvec(W, [x[i] - x_des[i] for i in range(n)])
    if m:
        gt = rmatvec_t(G, lam, n)
        g = [g[i] + gt[i] for i in range(n)]
    free = [~(((x[i] <= lower[i]) & (g[i] > tol_g)) | ((x[i] >= upper[i]) & (g[i] < -tol_g))) & (lower[i] < upper[i])
            for i in range(n)]
    dxa = [jnp.where(free[i], 0.0, jnp.where(x[i] <= 0.5 * (lower[i] + upper[i]), dl[i], du[i])) for i in range(n)]
    e = [x[i] - x_des[i] for i in range(n)]
    wd, dwe, wdxa = rmatvec(W, dxd), rmatvec(dW, e), rmatvec(W, dxa)
    dgl = rmatvec_t(dG, lam, n) if m else [0.0] * n
    r = [wd[i] - dwe[i] - dgl[i] - wdxa[i] for i in range(n)]
    s = [dh[j] - rdot(dG[j], x) - rdot(G[j], dxa) for j in range(m)]
    rows = [(lam[j] > 0) | eq[j] for j in range(m)]
    dy, _ = qp_pdas.kkt_solve_rows(W, G, free, rows, r, s)
    return [dy[i] + dxa[i] for i in range(n)]


@jax.custom_jvp
def _attach(x, lam, x_des, lower, upper, W, G, h, eq):
    """``x`` (the solution, computed without derivatives), with the implicit derivative attached."""
    return x


@_attach.defjvp
def _attach_jvp(primals, tangents):
    x, lam, x_des, lower, upper, W, G, h, eq = primals
    _, _, dxd, dl, du, dW, dG, dh, _ = tangents
    n, m = x.shape[-1], lam.shape[-1]
    if n <= UNROLL_MAX:
        rows = qp_pdas.to_rows
        mats = qp_pdas.to_mat_rows
        prim = (rows(x_des), rows(lower), rows(upper), W, mats(G), rows(h))  # W: row form already
        tang = (rows(dxd), rows(dl), rows(du), dW, mats(dG), rows(dh))
        dx = _tangent_rows(rows(x), rows(lam), prim, tang, rows(eq))
        dx = qp_pdas.from_rows(dx, x.shape[:-1], x.dtype)
    else:
        def one(x1, lam1, prim, tang, eq1):
            return _tangent(x1, lam1, prim, tang, _scales(*prim)[1], eq1)

        dx = jax.vmap(one)(x, lam, (x_des, lower, upper, W, G, h), (dxd, dl, du, dW, dG, dh), eq)
    return x, dx


# --------------------------------------------------------------------------------------------
# the batch


def _fast(x_des, lower, upper, W, G, h, max_iter, stop_count):
    """The fast path on the flat batch: ``(x, lam, settled, iterations)`` (arrays).

    ``W``: row form (lists) for ``n <= UNROLL_MAX``, else ``(B, n, n)``; symmetric.
    """
    B, n = x_des.shape
    m = G.shape[1]
    if n <= UNROLL_MAX:
        rows, mats = qp_pdas.to_rows, qp_pdas.to_mat_rows
        args = (rows(x_des), rows(lower), rows(upper), W, mats(G), rows(h))
        tols = qp_pdas.scales_rows(*args)
        x, lam, settled, it = qp_pdas.bpp_rows(*args, tols, max_iter, stop_count)
        return qp_pdas.from_rows(x, (B,), x_des.dtype), qp_pdas.from_rows(lam, (B,), x_des.dtype), settled, it

    def one(xd, lo, hi, w, g, hh):
        return qp_pdas.bpp_array(xd, lo, hi, w, g, hh, _scales(xd, lo, hi, w, g, hh), max_iter, _kkt_solve)

    return jax.vmap(one)(x_des, lower, upper, W, G, h)


def _chunk(B: int) -> int:
    """Problems handed to the robust path at a time (and the fast path's early-stop count)."""
    return min(B, max(16, B // 64))


@jax.jit
def _dense_batched(x_des, lower, upper, W, G, h, max_iter):
    """All problems of a batch (inputs broadcast to ``batch + core`` shapes), one compiled program.

    ``max_iter`` is traced (an int32 scalar): changing it does not recompile.
    """
    batch = x_des.shape[:-1]
    n, m = x_des.shape[-1], G.shape[-2]
    B = int(np.prod(batch)) if batch else 1
    x_des, lower, upper = (a.reshape(B, n) for a in (x_des, lower, upper))
    W, G, h = W.reshape(B, n, n), G.reshape(B, m, n), h.reshape(B, m)
    infeasible = jnp.zeros((B,), bool)
    lo, hi, Gp, hp = lower, upper, G, h
    if m == 1:  # closed form: a row no box point meets is pinned to its face (differentiable)
        lo, hi, Gp, hp, infeasible = jax.vmap(_pin_infeasible_rows)(lower, upper, G, h)

    # the metric, symmetrised once in the layout the solver reads: row form (one transpose)
    if n <= UNROLL_MAX:
        Wt = qp_pdas.to_mat_rows(W)
        Ws = [[0.5 * (Wt[i][j] + Wt[j][i]) for j in range(n)] for i in range(n)]
    else:
        Ws = 0.5 * (W + jnp.swapaxes(W, -1, -2))
    sg = [jax.lax.stop_gradient(a) for a in (x_des, lo, hi, W, Gp, hp)]
    chunk = _chunk(B)
    # rows make the fast path's iterations dearer and its tail longer: hand off earlier
    x, lam, ok, it = _fast(sg[0], sg[1], sg[2], jax.lax.stop_gradient(Ws), sg[4], sg[5], max_iter,
                           chunk if m == 0 else 4 * chunk)
    x, lam, ok, it, split = _fallback(sg, x, lam, ok, it, max_iter, chunk)  # (symmetrises its W)
    x, lam = jax.lax.stop_gradient(x), jax.lax.stop_gradient(lam)

    eq = jnp.zeros((B, m), bool)
    if m >= 2:  # the problem actually solved where some rows cannot hold together (differentiable)
        relax, zfree, zup, pin_l, pin_u, drop, eq = split
        r = jax.lax.cond(jnp.any(relax), lambda a: jax.vmap(qp_bvls.residual)(*a)[0], lambda a: jnp.zeros_like(a[3]),
                         (lower, upper, G, h, zfree, zup))
        infeasible = relax
        lo = jnp.where(pin_u, upper, lower)
        hi = jnp.where(pin_l, lower, upper)
        Gp = jnp.where(drop[..., None], 0.0, G)
        hp = jnp.where(drop, 0.0, h + jnp.where(relax[:, None], r, 0.0))
    x = _attach(x, lam, x_des, lo, hi, Ws, Gp, hp, eq)
    x = jnp.minimum(jnp.maximum(x, lower), upper)  # the box, exactly, whatever happened
    viol = jnp.max(jnp.maximum(jnp.einsum("bmn,bn->bm", G, x) - h, 0.0), axis=-1) if m else jnp.zeros((B,), x.dtype)
    res = BoxQPResult(x, ok, it.astype(jnp.int32), infeasible, viol)
    return jax.tree.map(lambda o: o.reshape(batch + o.shape[1:]), res)


def solve_box_qp(
    x_des,
    lower,
    upper,
    metric=None,
    *,
    G=None,
    h=None,
    gradient: str = "exact",
    max_iter: int | None = None,
) -> BoxQPResult:
    """Project ``x_des`` onto ``{lower <= x <= upper, G x <= h}`` in the metric ``W``.

    ``min_x 1/2 (x - x_des)^T W (x - x_des)  s.t.  lower <= x <= upper  [, G x <= h]``

    Args:
      x_des: ``(..., n)`` desired point (e.g. a joint acceleration [rad/s^2]); float32 or float64.
      lower, upper: the box, broadcastable to ``(..., n)``, finite, ``lower <= upper``.
      metric: ``None`` (identity), a 1-D positive diagonal ``(n,)``, or a dense symmetric positive
        definite matrix ``(..., n, n)``. Without halfspaces, ``None`` and a diagonal give the exact
        clip.
      G, h: optional halfspaces ``G x <= h``, ``G`` of shape ``(..., m, n)``, ``h`` of ``(..., m)``.
        When no box point meets every row, the box still holds exactly and the rows are met with
        the least violation: ``r* = max(G x - h, 0)`` of least Euclidean norm over the box (unique),
        and among the box points with that violation the metric decides (the projection onto
        ``{box, G x <= h + r*}``); ``infeasible`` is set, ``violation`` is ``max_j r*_j``. For one
        row this is the face of the box minimising ``G_j x``. The derivative is that of this
        answer (``r*`` included).
      gradient: ``"exact"`` — implicit derivative of the solution (true derivative; at a tie the
        coordinate is free, the derivative from inside the box). ``"straight_through"`` — the value
        is the same projection but the derivative w.r.t. ``x_des`` is the identity and w.r.t. the
        other inputs zero (a learning heuristic, not the derivative of the projection).
      max_iter: iterations per solve, for the fast path and again for the robust one (default
        ``4 n + 4 m + 10``); not static (no recompilation).

    Returns:
      ``BoxQPResult(x, converged, iterations, infeasible, violation)``. ``x`` satisfies the box
      exactly, always; it is never NaN for finite inputs. ``iterations``: fast-path iterations
      plus, for the problems handed to the robust path, its iterations.

    Raises (eagerly, concrete inputs): ``ValueError`` naming the field and value for bad shapes,
    ``lower > upper``, non-finite bounds/metric/halfspaces, a metric that is not symmetric positive
    definite, ``G`` without ``h`` or mismatched ``G``/``h``; ``ValueError`` for an unknown
    ``gradient``.
    """
    if gradient not in GRADIENTS:
        raise ValueError(f"gradient must be one of {GRADIENTS}, got {gradient!r}")
    x_des, lower, upper, metric, G, h, dtype = check_inputs(x_des, lower, upper, metric, G, h)
    n = x_des.shape[-1]
    if max_iter is None:
        max_iter = 4 * n + 4 * (0 if G is None else G.shape[-2]) + 10
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")

    dense = G is not None or (metric is not None and metric.ndim >= 2)
    shapes = [x_des.shape[:-1], lower.shape[:-1], upper.shape[:-1]]
    if metric is not None and metric.ndim >= 2:
        shapes.append(metric.shape[:-2])
    if G is not None:
        shapes += [G.shape[:-2], h.shape[:-1]]
    batch = jnp.broadcast_shapes(*shapes)
    full = batch + (n,)
    x_des, lower, upper = (jnp.broadcast_to(a, full) for a in (x_des, lower, upper))

    if not dense:
        x = _clip(x_des, lower, upper)
        res = BoxQPResult(x, jnp.ones(batch, bool), jnp.zeros(batch, jnp.int32), jnp.zeros(batch, bool), jnp.zeros(batch, dtype))
    else:
        if metric is None:
            W = jnp.eye(n, dtype=dtype)
        elif metric.ndim == 1:
            W = jnp.diag(metric)
        else:
            W = metric
        W = jnp.broadcast_to(W, batch + (n, n))
        if G is None:
            G = jnp.zeros(batch + (0, n), dtype)
            h = jnp.zeros(batch + (0,), dtype)
        m = G.shape[-2]
        G = jnp.broadcast_to(G, batch + (m, n))
        h = jnp.broadcast_to(h, batch + (m,))

        res = _dense_batched(x_des, lower, upper, W, G, h, jnp.int32(max_iter))
    if gradient == "straight_through":
        # value exactly res.x (x_des - x_des == 0), derivative the identity w.r.t. x_des
        res = res._replace(x=jax.lax.stop_gradient(res.x) + (x_des - jax.lax.stop_gradient(x_des)))
    return res


def project_box(x_des, lower, upper, metric=None, *, G=None, h=None, gradient: str = "exact",
                max_iter: int | None = None) -> jax.Array:
    """``solve_box_qp(...).x``: the projection alone (see ``solve_box_qp`` for every argument).

    Shape ``(..., n)``, the dtype of the inputs; ``lower <= x <= upper`` exactly.
    """
    return solve_box_qp(x_des, lower, upper, metric, G=G, h=h, gradient=gradient, max_iter=max_iter).x
