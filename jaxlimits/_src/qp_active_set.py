"""The robust path of the box-QP, for one problem: the primal active-set method, and the least violation.

``qp.py`` runs ``solve`` (vmapped) on the few problems the fast path (``qp_pdas``) did not settle
within ``max_iter``: for ``m >= 2`` the least violation of the rows first (``qp_bvls``), then the
primal active-set method (``active_set_solve``) from a feasible point, on the set of least
violation. ``pin_infeasible_rows`` is the closed form of the least violation of one row (``m == 1``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxlimits._src import qp_bvls
from jaxlimits._src.qp_linalg import active_free, chol_apply, chol_factor, kkt_solve, masked_matrix, scales


class Split(NamedTuple):
    """The problem actually solved where rows cannot all hold (``m >= 2``; all False otherwise).

    relax: ``()`` bool, some row cannot hold (certified; ``h`` is relaxed by ``r*``). zfree, zup:
    ``(n + m,)`` bool, the final BVLS split of ``(x, t)`` (``(0,)`` for ``m < 2``), from which
    ``r*`` is recomputed differentiably. pin_l, pin_u: ``(n,)`` bool, coordinates pinned to their
    lower / upper bound. drop: ``(m,)`` bool, rows dropped. eq: ``(m,)`` bool, rows held as
    equalities.
    """

    relax: jax.Array
    zfree: jax.Array
    zup: jax.Array
    pin_l: jax.Array
    pin_u: jax.Array
    drop: jax.Array
    eq: jax.Array


class Result(NamedTuple):
    """What ``solve`` returns for one problem.

    x: ``(n,)`` the solution (in the box). lam: ``(m,)`` row multipliers. ok: ``()`` bool, the
    KKT conditions (and the least violation) hold to the tolerances. it: ``()`` int32, active-set
    iterations. free: ``(n,)`` bool, the coordinates free in the derivative (``active_free``).
    split: ``Split``.
    """

    x: jax.Array
    lam: jax.Array
    ok: jax.Array
    it: jax.Array
    free: jax.Array
    split: Split


class _Working(NamedTuple):
    """The active-set method's loop state: y ``(n,)`` the iterate; hl, hu ``(n,)`` bool, bounds held;
    rows ``(m,)`` bool, rows held; lam ``(m,)`` their multipliers; it ``()`` int32; done ``()`` bool."""

    y: jax.Array
    hl: jax.Array
    hu: jax.Array
    rows: jax.Array
    lam: jax.Array
    it: jax.Array
    done: jax.Array


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
    C = jnp.where(rows[:, None], chol_apply(fac, B, unroll), 0.0)
    # one refinement step: removes the regularisation's error (relative reg * cond(S) otherwise)
    C = C + jnp.where(rows[:, None], chol_apply(fac, B - S0 @ C, unroll), 0.0)
    R = VF - C.T @ A
    tol = 1e3 * eps
    return jnp.sum(R * R, axis=1) <= tol * tol * jnp.sum(V * V, axis=1)


def _independent_rows(G, free, cand, eq):
    """A working set of rows: every ``eq`` row, then the ``cand`` rows (in index order) whose free
    part is independent of those already taken (modified Gram-Schmidt on the free coordinates, ``1e3 eps``).

    Two passes over the rows (``eq`` rows, then the others), as loops: unrolled, the ``O(m^2)`` projections
    were most of the robust path's trace and compile time (``m = 14`` on the shield's torque-space problems).
    ``basis`` ``(2 m, n)`` holds one unit vector per visit (zero where the row was not taken); subtracting a
    zero row is exact, so projecting on every earlier visit is the sequential method itself.
    """
    m, n = G.shape
    eps = jnp.finfo(G.dtype).eps
    GF = jnp.where(free[None, :], G, 0.0)

    def visit(t, carry):
        basis, take = carry
        second = t >= m
        j = t - jnp.where(second, m, 0)
        v = jax.lax.fori_loop(0, t, lambda k, v: v - (basis[k] @ v) * basis[k], GF[j])
        nv2 = v @ v
        indep = nv2 > (1e3 * eps) ** 2 * (G[j] @ G[j])
        take_j = jnp.where(second, eq[j] | (cand[j] & indep), eq[j])
        use = jnp.where(second, ~eq[j] & take_j, eq[j]) & indep
        basis = basis.at[t].set(jnp.where(use, v / jnp.sqrt(jnp.where(indep, nv2, 1.0)), 0.0))
        return basis, take.at[j].set(take_j)

    init = (jnp.zeros((2 * m, n), G.dtype), jnp.zeros((m,), bool))
    return jax.lax.fori_loop(0, 2 * m, visit, init)[1]


def active_set_solve(x_des, lower, upper, W, G, h, eq, start, max_iter, tols):
    """Primal active-set method on the box and the rows (working set: held bounds and rows).

    Each iteration solves the equality-constrained QP of the working set exactly (``kkt_solve``)
    and steps towards its solution ``z``: all the way if no constraint outside the working set
    blocks (then the multiplier of most negative sign, if any, is released), else up to the first
    blocking constraint, which joins the working set. The working set stays linearly independent: a
    constraint dependent on the held rows never blocks (``_dependent``), else exact duplicate rows
    cycle on rounding (a copy joins at a zero step, gets a negative multiplier, leaves, joins...).
    From a feasible point the objective never increases and no working set repeats, so it
    terminates (finitely, in exact arithmetic). ``start`` is a box point (meeting the rows, or
    violating held ones: they hold with equality after the first full step); the bounds it sits on
    and the rows it meets with equality (those independent of the ones taken before them,
    ``_independent_rows``) start in the working set. Rows in ``eq`` are equalities: always held,
    never released. Returns ``(x, lam, done, it)``.
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

    def body(s: _Working) -> _Working:
        y, hl, hu, rows = s.y, s.hl, s.hu, s.rows
        free = ~(hl | hu)
        xa = jnp.where(hl, lower, jnp.where(hu, upper, 0.0))
        zf, lam_z = kkt_solve(W, G, free, rows, wdx - W @ xa, h - G @ xa)
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
        add_l, add_u = add[:n], add[n : 2 * n]
        y_step = jnp.where(free, jnp.clip(y + a * d, lower, upper), y)
        y_full = jnp.where(free, jnp.clip(z, lower, upper), y)
        y_new = jnp.where(add_l, lower, jnp.where(add_u, upper, jnp.where(blocked, y_step, y_full)))
        hl2, hu2 = hl | add_l, hu | add_u
        rows2 = rows | add[2 * n :]
        # at the working-set optimum: release the most negative (scaled) multiplier, or stop
        g = W @ (y_new - x_des) + G.T @ lam_z
        mult = jnp.where(hl & ~flat, g / wd, jnp.where(hu, -g / wd, jnp.inf))
        cand = jnp.concatenate([mult, jnp.full((n,), jnp.inf, W.dtype), jnp.where(rows & ~eq, lam_z * gn, jnp.inf)])
        j = jnp.argmin(cand)
        neg = cand[j] < -tol_g / jnp.max(wd)
        release = ~blocked & neg & (idx == j)
        hl2 = hl2 & ~release[:n]
        hu2 = hu2 & ~release[:n]
        rows2 = rows2 & ~release[2 * n :]
        done = ~blocked & ~neg
        return _Working(y_new, hl2, hu2, rows2, jnp.where(rows2, lam_z, 0.0), s.it + 1, done)

    def cond(s: _Working):
        return (s.it < max_iter) & ~s.done

    init = _Working(y0, held_l0, held_u0, rows0, jnp.zeros((m,), W.dtype), jnp.int32(0), jnp.bool_(False))
    out = jax.lax.while_loop(cond, body, init)
    return out.y, out.lam, out.done, out.it


def pin_infeasible_rows(lower, upper, G, h):
    """Rows that no box point satisfies: pin their coordinates at the minimising bounds, drop them.

    ``min_{lower<=x<=upper} G_j x = sum_i min(G_ji lower_i, G_ji upper_i)`` is attained exactly on
    the face ``x_i = lower_i`` (``G_ji > 0``), ``x_i = upper_i`` (``G_ji < 0``); if it is ``>= h_j``
    that face is the set of least violation of row ``j`` (exactly its feasible set at equality).
    Used for ``m == 1`` (closed form); ``m >= 2`` goes through ``qp_bvls``. Returns
    ``(lower, upper, G, h, infeasible)`` of the problem to solve (``infeasible``: ``()`` bool).
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
    # a tight row pins only the coordinates that could move it by more than the tolerance it was found
    # tight at: a rounding-level coefficient (a float32 mass matrix's 1e-9 off-diagonals) pinned every
    # coordinate of the row at the face it minimises, however far the answer lies from it
    moves = jnp.abs(G) * jnp.where(jnp.isfinite(upper - lower), upper - lower, jnp.inf)[None, :] > 30.0 * tol_h[:, None]
    pl2 = jnp.any(tight[:, None] & (G > 0) & moves, axis=0)
    pu2 = jnp.any(tight[:, None] & (G < 0) & moves, axis=0) & ~pl2
    pin_l = pin_l | (~pin_u & pl2)
    pin_u = pin_u | (~pin_l & pu2)
    pinned = pin_l | pin_u | (lower >= upper)
    GF = jnp.where(pinned[None, :], 0.0, G)
    drop = tight | (jnp.sum(GF * GF, axis=1) <= eps * eps * jnp.sum(G * G, axis=1))
    J = relax & (r > 30.0 * tol_h) & ~drop
    j0 = jnp.argmax(jnp.where(J, r, -1.0))
    drop0 = J & (jnp.arange(m) == j0) & (jnp.sum(J) >= 2)
    return pin_l, pin_u, drop | drop0, J & ~drop0


def solve(x_des, lower, upper, W, G, h, x_warm, max_iter) -> Result:
    """The robust path for one problem (``W``: its symmetric part is the metric; ``x_warm`` ``(n,)`` the
    fast path's last iterate).

    ``m >= 2``: the least violation ``r*`` first (``qp_bvls``); ``relax`` when some row cannot
    hold (``r* > 0``), then the problem is solved on the set of least violation
    (``_least_violation_split``) from the BVLS point. The returned ``split`` describes the problem
    actually solved, for the derivative.
    """
    n, m = W.shape[0], G.shape[0]
    W = 0.5 * (W + W.T)
    tols = scales(x_des, lower, upper, W, G, h)
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
        # the certificate is homogeneous in r: taken for r / max(r), so a row ~1e30 out of reach (r ~ 1e30,
        # ||r||^2 beyond float32) does not make gap and err inf (and the problem look feasible)
        k = 1.0 / jnp.where(jnp.max(r) > 0, jnp.max(r), 1.0)
        rs = r * k
        gap, err = qp_bvls.certificate(lower, upper, G, h, rs)
        relax = jnp.any(r > 30.0 * tols[2]) & (gap > 16.0 * err)
        rr = jnp.where(relax, r, 0.0)
        # r is the least violation to rounding: ||r||^2 - gap = sum_i |q_i| dist(x_i, its bound)
        # at the BVLS point, rounding-level where q_i ~ 0 (q_i's rounding: the rows' own scales); all of it
        # divided by max(r)^2
        s = qp_bvls.row_scale(lower, upper, G, h) * k
        eps = jnp.finfo(W.dtype).eps
        lv_tol = 1e3 * (err * k + eps * (n + m) * jnp.sum(jnp.where(r > 0, s * s, 0.0)))
        lv_ok = ~relax | (rs @ rs - gap * k <= lv_tol)
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
    tols = scales(x_des, lo, hi, W, Ge, he)
    x, lam, done, it = active_set_solve(x_des, lo, hi, W, Ge, he, eq, start, max_iter, tols)
    x = jnp.clip(x, lo, hi)
    ok = done & _kkt_ok(x, x_des, lo, hi, W, Ge, he, lam, tols, eq) & lv_ok
    if m:  # every row as given (dropped and pinned ones too) holds at x, relaxed by r* if infeasible
        tol_h = scales(x_des, lower, upper, W, G, h + rr)[2]
        slack = 30.0 * tol_h + 32.0 * jnp.finfo(W.dtype).eps * (jnp.abs(G) @ jnp.abs(x))
        ok = ok & jnp.all(G @ x - (h + rr) <= slack)
    free = active_free(x, lo, hi, W @ (x - x_des) + Ge.T @ lam, tols[1])
    return Result(x, lam, ok, it, free, Split(relax, zfree, zup, pin_l, pin_u, drop, eq))
