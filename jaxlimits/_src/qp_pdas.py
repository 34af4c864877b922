"""The fast path of the box-QP: block principal pivoting (a primal-dual active-set method).

For every problem the coordinates are split into free / held at ``lower`` / held at ``upper`` and
the rows of ``G x <= h`` into held (equality) / free. One iteration solves the equality-constrained
QP of the current split exactly (masked Cholesky of ``W_FF`` and an ``m x m`` Schur complement for
the held rows) and looks at the *infeasibilities* of that solution: a free coordinate outside its
box, a free row violated (primal), a held bound or row with a negative multiplier (dual). None
left: the solution satisfies every KKT condition to the tolerances and the problem is settled.
Otherwise the split is changed:

* block pivot: every infeasible variable flips (free -> the violated bound / row held, held ->
  free), as long as the number of infeasibilities keeps decreasing, or for ``BUDGET`` tries;
* else Murty's single pivot: only the infeasible variable of least index flips.

This is the safeguarded block principal pivoting of Judice & Pires (1994) (Kim & Park 2011 for
NNLS); for a positive definite metric without rows (a P-matrix LCP) it terminates finitely. From
the clip's split it settles in 1-6 iterations on well-conditioned problems (n = 7, condition 1e2);
ill-conditioned metrics need more. ``qp.py`` stops it early once only a few problems of the batch
are left and hands those to the robust primal active-set method.

Two implementations of the same iteration: *row form* (``n <= UNROLL_MAX``; the batch is the
vector dimension of scalar code on Python lists, see ``qp_linalg``) and *array form* (one problem,
vmapped; LAPACK Cholesky) for larger ``n``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxlimits._src.qp_linalg import rchol, rchol_solve, rdot, rmatvec, rmatvec_t

BUDGET = 3  # block pivots allowed without a decrease of the infeasibility count


def _rmax(values):
    return functools.reduce(jnp.maximum, values)


def _rany(values):
    return functools.reduce(jnp.logical_or, values) if values else False


def _runtime_one(it, dtype):
    """1.0, computed from a loop counter so that XLA cannot fold a division by it."""
    k = (it + 1).astype(dtype)
    return k / k


def _keep(v, one):
    """``v`` through a division by ``one`` (see ``bpp_rows``)."""
    return v / one




def _rsum_int(values):
    return functools.reduce(jnp.add, [v.astype(jnp.int32) for v in values])


# --------------------------------------------------------------------------------------------
# layout


def to_rows(a):
    """``(..., k)`` -> list of ``k`` arrays ``(...)`` (through a transpose: the batch contiguous)."""
    at = jnp.moveaxis(a, -1, 0)
    return [at[i] for i in range(at.shape[0])]


def to_mat_rows(A):
    """``(..., p, q)`` -> list (p) of lists (q) of ``(...)`` arrays, batch contiguous."""
    At = jnp.moveaxis(A, (-2, -1), (0, 1))
    return [[At[i, j] for j in range(At.shape[1])] for i in range(At.shape[0])]


def from_rows(rows, batch, dtype):
    """List of ``k`` arrays ``batch`` -> ``batch + (k,)``."""
    if not rows:
        return jnp.zeros(batch + (0,), dtype)
    return jnp.stack([jnp.broadcast_to(r, batch) for r in rows], axis=-1)


# --------------------------------------------------------------------------------------------
# row form


def scales_rows(xd, lo, hi, W, G, h):
    """``qp._scales`` in row form: ``(tol_x, tol_g, [tol_h_j])``."""
    n = len(xd)
    dt = jnp.result_type(xd[0])
    eps = jnp.finfo(dt).eps
    cl = [jnp.clip(xd[i], lo[i], hi[i]) for i in range(n)]
    sx = 1.0 + _rmax([jnp.abs(c) for c in cl]) + _rmax([jnp.abs(xd[i] - cl[i]) for i in range(n)])
    sw = _rmax([jnp.abs(w) for row in W for w in row])
    tol_x = 32.0 * eps * sx
    tol_g = 4.0 * eps * sw * sx * n
    tol_h = [32.0 * eps * (_rmax([jnp.abs(g) for g in row]) * sx * n + jnp.abs(hj)) for row, hj in zip(G, h)]
    return tol_x, tol_g, tol_h


def kkt_solve_rows(W, G, free, rows, r, s):
    """Row form of ``qp._kkt_solve``: ``W_FF y_F + G_RF^T lam_R = r_F``, ``G_RF y_F = s_R``.

    Returns ``(y, lam)`` (0 on held coordinates and on rows not in ``rows``).
    """
    n, m = len(W), len(G)
    dt = jnp.result_type(W[0][0])
    eps = jnp.finfo(dt).eps
    M = [[jnp.where(free[i], W[i][i], 1.0) if i == j else jnp.where(free[i] & free[j], W[i][j], 0.0)
          for j in range(n)] for i in range(n)]
    L = rchol(M)
    y = rchol_solve(L, [jnp.where(free[i], r[i], 0.0) for i in range(n)])
    if m == 0:
        return y, []
    GF = [[jnp.where(free[i], G[j][i], 0.0) for i in range(n)] for j in range(m)]
    # a row whose free part vanishes is fixed by the box alone: nothing to solve for it
    rows = [rows[j] & (rdot(GF[j], GF[j]) > eps * eps * rdot(G[j], G[j])) for j in range(m)]
    GF = [[jnp.where(rows[j], g, 0.0) for g in GF[j]] for j in range(m)]
    Z = [rchol_solve(L, GF[j]) for j in range(m)]  # apart from y: y is linear in tangents, Z is not
    S = [[rdot(GF[j], Z[k]) for k in range(m)] for j in range(m)]
    reg = 1e2 * eps * (_rmax([jnp.abs(S[j][j]) for j in range(m)]) + jnp.finfo(dt).tiny)
    Sm = [[jnp.where(rows[j], S[j][j], 1.0) + reg if j == k else jnp.where(rows[j] & rows[k], S[j][k], 0.0)
           for k in range(m)] for j in range(m)]
    Ls = rchol(Sm)
    lam = rchol_solve(Ls, [jnp.where(rows[j], rdot(GF[j], y) - s[j], 0.0) for j in range(m)])
    lam = [jnp.where(rows[j], lam[j], 0.0) for j in range(m)]
    x = [y[i] - rdot([Z[j][i] for j in range(m)], lam) for i in range(n)]
    # one refinement step (see qp._kkt_solve)
    dlam = rchol_solve(Ls, [jnp.where(rows[j], rdot(GF[j], x) - s[j], 0.0) for j in range(m)])
    lam = [jnp.where(rows[j], lam[j] + dlam[j], 0.0) for j in range(m)]
    x = [jnp.where(free[i], y[i] - rdot([Z[j][i] for j in range(m)], lam), 0.0) for i in range(n)]
    return x, lam


def bpp_rows(xd, lo, hi, W, G, h, tols, max_iter, stop_count):
    """Block principal pivoting on a batch in row form (see the module docstring).

    ``xd, lo, hi``: lists of ``n`` arrays of the batch shape ``(B,)``; ``W`` n x n, ``G`` m x n
    lists; ``h`` a list of ``m``. The loop runs while more than ``stop_count`` problems are not
    settled, at most ``max_iter`` iterations. Returns ``(x, lam, settled, iterations)`` (``x`` not
    clipped; for a settled problem it is its solution).
    """
    n, m = len(xd), len(h)
    _, tol_g, tol_h = tols
    batch = jnp.shape(xd[0])
    eps = jnp.finfo(jnp.result_type(xd[0])).eps
    flat = [lo[i] >= hi[i] for i in range(n)]
    c = rmatvec(W, xd)
    gn = [jnp.sqrt(rdot(G[j], G[j])) for j in range(m)]
    cl = [jnp.clip(xd[i], lo[i], hi[i]) for i in range(n)]
    hl0 = [flat[i] | (xd[i] < lo[i]) for i in range(n)]
    hu0 = [~flat[i] & (xd[i] > hi[i]) for i in range(n)]
    ra0 = [rdot(G[j], cl) - h[j] > tol_h[j] for j in range(m)]
    # a held bound is released when its multiplier is wrong by more than the rounding of its own
    # g_i = sum_j W_ij (x_j - x_des_j) (bounded per coordinate; tol_g is the global bound)
    span = [jnp.abs(xd[j]) + jnp.maximum(jnp.abs(lo[j]), jnp.abs(hi[j])) for j in range(n)]
    tol_r = [jnp.minimum(tol_g, 8.0 * eps * rdot([jnp.abs(w) for w in W[i]], span)) for i in range(n)]
    # likewise the rounding of G_j x - h_j over the box (tol_h is a looser global bound)
    bnd = [jnp.maximum(jnp.abs(lo[i]), jnp.abs(hi[i])) for i in range(n)]
    tol_row = [jnp.minimum(tol_h[j], 8.0 * eps * (rdot([jnp.abs(g) for g in G[j]], bnd) + jnp.abs(h[j])))
               for j in range(m)]

    def body(state):
        hl, hu, ra, _, _, it, settled, iters, best, budget = state
        one = _runtime_one(it, jnp.result_type(xd[0]))
        free = [~(hl[i] | hu[i]) for i in range(n)]
        xa = [jnp.where(hl[i], lo[i], jnp.where(hu[i], hi[i], 0.0)) for i in range(n)]
        wxa = rmatvec(W, xa)
        y, lam = kkt_solve_rows(W, G, free, ra, [c[i] - wxa[i] for i in range(n)],
                                [h[j] - rdot(G[j], xa) for j in range(m)])
        x = [y[i] + xa[i] for i in range(n)]
        g = rmatvec(W, [x[i] - xd[i] for i in range(n)])
        if m:
            gt = rmatvec_t(G, lam, n)
            g = [_keep(g[i] + gt[i], one) for i in range(n)]  # read by every coordinate's pivot below
        # a free variable joins at any violation, a held one leaves only beyond the tolerance
        # (ties settle where they are instead of flipping back and forth)
        bad_l = [free[i] & (x[i] < lo[i]) for i in range(n)]
        bad_u = [free[i] & (x[i] > hi[i]) for i in range(n)]
        viol = [rdot(G[j], x) - h[j] > 0.0 for j in range(m)]
        # a held row that is still violated ("lost": no free coordinate left in it, or held rows
        # that contradict each other) cannot be met with these bounds held: release the held
        # bounds that keep it violated, as if their multipliers had the wrong sign (none: the row
        # cannot hold on this face and flips out like a wrong multiplier)
        push, stuck = [False] * n, []
        for j in range(m):
            cand = [~flat[i] & ((hu[i] & (G[j][i] > 0)) | (hl[i] & (G[j][i] < 0))) for i in range(n)]
            res = rdot(G[j], x) - h[j]
            gf = rdot([jnp.where(free[i], G[j][i], 0.0) for i in range(n)], [jnp.where(free[i], G[j][i], 0.0) for i in range(n)])
            lost = ra[j] & (((res > tol_row[j]) & (gf <= eps * eps * rdot(G[j], G[j]))) | (res > 100.0 * tol_row[j]))
            lost = _keep(jnp.where(lost, 1.0, 0.0), one) > 0.0
            push = [push[i] | (lost & cand[i]) for i in range(n)]
            stuck.append(lost & ~_rany(cand))
        bad_h = [~flat[i] & ((hl[i] & (g[i] < -tol_r[i])) | (hu[i] & (g[i] > tol_r[i])) | push[i]) for i in range(n)]
        bad_r = [(~ra[j] & viol[j]) | (ra[j] & (lam[j] * gn[j] < -tol_g)) | stuck[j] for j in range(m)]
        # materialise the verdicts once (a division is "expensive": XLA stops duplicating the
        # whole iteration into every consumer of the pivot logic below)
        code = [_keep(jnp.where(bad_l[i], 1.0, jnp.where(bad_u[i], 2.0, jnp.where(bad_h[i], 3.0, 0.0))), one)
                for i in range(n)] + [_keep(jnp.where(bad_r[j], 1.0, 0.0), one) for j in range(m)]
        bad_l = [code[i] == 1.0 for i in range(n)]
        bad_u = [code[i] == 2.0 for i in range(n)]
        bad_h = [code[i] == 3.0 for i in range(n)]
        bad = [c > 0.0 for c in code]
        count = _rsum_int(bad)
        improve = count < best
        block = improve | (budget > 0)
        best = jnp.where(improve, count, best)
        budget = jnp.where(improve, BUDGET, jnp.where(block, budget - 1, budget))
        # the pivot, as one materialised number: -1 block pivot, else the index of the first
        # infeasible variable (Murty)
        first = float(n + m)
        for k in reversed(range(n + m)):
            first = jnp.where(bad[k], float(k), first)
        piv = _keep(jnp.where(block, -1.0, first), one)
        flip = [bad[k] & ((piv == -1.0) | (piv == float(k))) for k in range(n + m)]
        nhl = [(hl[i] & ~(flip[i] & bad_h[i])) | (flip[i] & bad_l[i]) for i in range(n)]
        nhu = [(hu[i] & ~(flip[i] & bad_h[i])) | (flip[i] & bad_u[i]) for i in range(n)]
        nra = [ra[j] ^ flip[n + j] for j in range(m)]
        iters = jnp.where(settled, iters, it + 1)
        return nhl, nhu, nra, x, lam, it + 1, count == 0, iters, best, budget

    def cond(state):
        return (state[5] < max_iter) & (jnp.sum(~state[6]) > stop_count)

    zero = jnp.zeros(batch, jnp.result_type(xd[0]))
    izero = jnp.zeros(batch, jnp.int32)
    init = (hl0, hu0, ra0, [zero] * n, [zero] * m, jnp.int32(0), jnp.zeros(batch, bool), izero,
            izero + (n + m + 1), izero + BUDGET)
    state = jax.lax.while_loop(cond, body, init)
    x, lam, settled, iters = state[3], state[4], state[6], state[7]
    return x, lam, settled, iters


# --------------------------------------------------------------------------------------------
# array form (one problem; vmapped by the caller)


def bpp_array(x_des, lower, upper, W, G, h, tols, max_iter, kkt_solve):
    """The same iteration for one problem with arrays (``kkt_solve``: ``qp._kkt_solve``).

    Returns ``(x, lam, settled, iterations)``. Under ``vmap`` the loop runs until every problem
    of the batch has settled or ``max_iter``.
    """
    _, tol_g, tol_h = tols
    n, m = W.shape[0], G.shape[0]
    eps = jnp.finfo(x_des.dtype).eps
    flat = lower >= upper
    c = W @ x_des
    gn = jnp.sqrt(jnp.sum(G * G, axis=1))
    hl0 = flat | (x_des < lower)
    hu0 = ~flat & (x_des > upper)
    ra0 = G @ jnp.clip(x_des, lower, upper) - h > tol_h
    span = jnp.abs(x_des) + jnp.maximum(jnp.abs(lower), jnp.abs(upper))
    tol_r = jnp.minimum(tol_g, 8.0 * eps * (jnp.abs(W) @ span))
    tol_row = jnp.minimum(tol_h, 8.0 * eps * (jnp.abs(G) @ jnp.maximum(jnp.abs(lower), jnp.abs(upper)) + jnp.abs(h)))

    def body(state):
        hl, hu, ra, _, _, it, _, best, budget = state
        free = ~(hl | hu)
        xa = jnp.where(hl, lower, jnp.where(hu, upper, 0.0))
        y, lam = kkt_solve(W, G, free, ra, c - W @ xa, h - G @ xa)
        x = y + xa
        g = W @ (x - x_des) + G.T @ lam
        bad_l = free & (x < lower)
        bad_u = free & (x > upper)
        viol = G @ x - h > 0.0
        cand = ~flat[None, :] & ((hu[None, :] & (G > 0)) | (hl[None, :] & (G < 0)))
        res = G @ x - h
        gf = jnp.sum(jnp.where(free[None, :], G, 0.0) ** 2, axis=1)
        lost = ra & (((res > tol_row) & (gf <= eps * eps * jnp.sum(G * G, axis=1))) | (res > 100.0 * tol_row))
        push = jnp.any(lost[:, None] & cand, axis=0)
        stuck = lost & ~jnp.any(cand, axis=1)
        bad_h = ~flat & ((hl & (g < -tol_r)) | (hu & (g > tol_r)) | push)
        bad_r = (~ra & viol) | (ra & (lam * gn < -tol_g)) | stuck
        bad = jnp.concatenate([bad_l | bad_u | bad_h, bad_r])
        count = jnp.sum(bad, dtype=jnp.int32)
        improve = count < best
        block = improve | (budget > 0)
        best = jnp.where(improve, count, best)
        budget = jnp.where(improve, BUDGET, jnp.where(block, budget - 1, budget))
        first = bad & (jnp.cumsum(bad.astype(jnp.int32)) == 1)
        flip = jnp.where(block, bad, first)
        fb, fr = flip[:n], flip[n:]
        nhl = (hl & ~(fb & bad_h)) | (fb & bad_l)
        nhu = (hu & ~(fb & bad_h)) | (fb & bad_u)
        return nhl, nhu, ra ^ fr, x, lam, it + 1, count == 0, best, budget

    def cond(state):
        return (state[5] < max_iter) & ~state[6]

    dt = x_des.dtype
    init = (hl0, hu0, ra0, jnp.zeros((n,), dt), jnp.zeros((m,), dt), jnp.int32(0), jnp.bool_(False),
            jnp.int32(n + m + 1), jnp.int32(BUDGET))
    state = jax.lax.while_loop(cond, body, init)
    return state[3], state[4], state[6], state[5]
