"""Least violation of halfspaces over a box (phase 1 of the infeasible case, ``m >= 2``).

``min_{lower <= x <= upper} 1/2 ||max(G x - h, 0)||^2`` written as a bounded-variable least-squares
problem in ``z = (x, t)``:

    min 1/2 ||G x - t - h||^2   s.t.   lower <= x <= upper,   t <= 0,

(at the optimum ``t = min(G x - h, 0)``, so the residual ``r = G x - t - h = max(G x - h, 0)``).
Solved by the active-set method of Lawson & Hanson / Stark & Parker (BVLS): start with every
variable at a bound; repeatedly free the bound variable whose gradient points most into its box,
solve the least-squares problem of the free variables exactly, and step back to the first bound hit
if that solution leaves the box. It terminates finitely (in exact arithmetic) at a minimiser. A
row whose ``t`` is free is met exactly (``t_j = G_j x - h_j``), so it is eliminated: the normal
equations (masked Cholesky) hold only the rows with ``t`` held, and tolerances are per row
(``row_scale``). (Solving for ``(x, t)`` together let the rounding of far-away rows, huge ``h_j``,
leak into the residual of the near ones: a feasible problem then looked infeasible.) The residual
``r*`` is unique even when the minimiser is not (strict convexity of the squared norm in ``r``), so
the set of least violation is ``{x in box : G x <= h + r*}``.

Array form, one problem (the caller vmaps). Only problems that the fast path could not settle go
through here.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxlimits._src.qp_linalg import chol_solve, masked_matrix


def _system(lower, upper, G):
    m, n = G.shape
    dt = G.dtype
    A = jnp.concatenate([G, -jnp.eye(m, dtype=dt)], axis=1)
    zl = jnp.concatenate([lower, jnp.zeros((m,), dt)])  # t has no lower bound (never held there)
    zu = jnp.concatenate([upper, jnp.zeros((m,), dt)])
    has_l = jnp.concatenate([jnp.ones((n,), bool), jnp.zeros((m,), bool)])
    return A, zl, zu, has_l


def row_scale(lower, upper, G, h):
    """Per row, the magnitude of ``G_j x - h_j`` over the box: ``|h_j| + sum_i |G_ji| max(|l_i|, |u_i|)``.

    The rounding of a row's value anywhere in the box is a few ulps of this; tolerances are per
    row (a far-away row, huge ``h_j``, must not loosen the others).
    """
    return jnp.abs(h) + jnp.abs(G) @ jnp.maximum(jnp.abs(lower), jnp.abs(upper))


def _ls(G, h, free_x, held_t, x):
    """``x`` moved to ``argmin ||G_R x - h_R||`` over its free coordinates, ``R`` = rows with ``t`` held.

    Rows with a free ``t`` are met exactly (``t_j = G_j x - h_j``) and drop out of the normal
    equations: their right-hand sides (possibly huge, far-away rows) never enter the rounding of
    the others. Solved for the step from ``x`` (directions the rows do not see stay put).
    """
    GR = jnp.where(held_t[:, None] & free_x[None, :], G, 0.0)
    N = masked_matrix(GR.T @ GR, free_x)
    res = jnp.where(held_t, h - G @ x, 0.0)
    return x + jnp.where(free_x, chol_solve(N, jnp.where(free_x, GR.T @ res, 0.0), unroll=False), 0.0)


def residual(lower, upper, G, h, free, at_u):
    """``(r*, x)`` of the least-squares problem of a final BVLS split (``free``, ``at_u``).

    Written with ordinary differentiable operations: the derivative of ``r*`` w.r.t. the box and
    the halfspaces (the split held fixed) is that of the least violation. ``r*_j = 0`` exactly on
    rows whose ``t`` is free (met with slack).
    """
    n = G.shape[1]
    free_x, held_t = free[:n], ~free[n:]
    xb = jnp.where(free_x, 0.0, jnp.where(at_u[:n], upper, lower))
    x = _ls(G, h, free_x, held_t, xb)
    return jnp.where(held_t, jnp.maximum(G @ x - h, 0.0), 0.0), x


def certificate(lower, upper, G, h, r):
    """``(gap, err)`` for a candidate least violation ``r >= 0``; ``q = G^T r``.

    ``gap = min_box q.x - r.h``. Any box point ``y`` meeting every row gives
    ``r.(G y - h) <= 0``, so ``gap > 0`` (beyond its rounding ``err``) proves that no box point
    meets the rows (Farkas). At the least violation ``r*`` the gap is ``||r*||^2`` (phase-1
    optimality), and ``gap / ||r||`` bounds the violation norm of every box point from below,
    so ``||r||^2 - gap`` measures how far ``r`` is from optimal. ``err = eps (n + m) sum_j r_j s_j``
    (``s`` from ``row_scale``) is a few times the rounding of ``gap``.
    """
    m, n = G.shape
    q = G.T @ r
    gap = jnp.sum(jnp.minimum(q * lower, q * upper)) - r @ h
    err = jnp.finfo(G.dtype).eps * (n + m) * (r @ row_scale(lower, upper, G, h))
    return gap, err


class _Split(NamedTuple):
    """BVLS's loop state for ``z = (x, t)``: z ``(n + m,)`` the point; free, at_u ``(n + m,)`` bool,
    the variables free / held at their upper bound (else at their lower one); it ``()`` int32;
    done ``()`` bool."""

    z: jax.Array
    free: jax.Array
    at_u: jax.Array
    it: jax.Array
    done: jax.Array


def bvls(lower, upper, G, h, max_iter):
    """BVLS for one problem. Returns ``(free, at_u, z, done)``: the final split of ``(x, t)`` and point."""
    m, n = G.shape
    dt = G.dtype
    eps = jnp.finfo(dt).eps
    A, zl, zu, has_l = _system(lower, upper, G)
    fixed = jnp.concatenate([lower >= upper, jnp.zeros((m,), bool)])
    colnorm = jnp.sqrt(jnp.sum(A * A, axis=0)) + jnp.finfo(dt).tiny
    # rounding of each variable's gradient, per row (see ``row_scale``): a row's t stays held
    # while the row is met within its own rounding, x_i sees the rounding of the rows it enters
    s = 32.0 * eps * (n + m) * row_scale(lower, upper, G, h) + jnp.finfo(dt).tiny
    up0 = jnp.sum(G, axis=0) <= 0  # each x at the bound that lowers the rows on the whole
    at_u0 = jnp.concatenate([up0 & ~(lower >= upper), jnp.ones((m,), bool)])
    z0 = jnp.where(at_u0, zu, zl)
    inf = jnp.asarray(jnp.inf, dt)

    def body(c: _Split) -> _Split:
        z, free, at_u = c.z, c.free, c.at_u
        free_x, held_t = free[:n], ~free[n:]
        x = _ls(G, h, free_x, held_t, z[:n])
        y = jnp.concatenate([x, jnp.where(held_t, z[n:], G @ x - h)])
        d = jnp.where(free, y - z, 0.0)
        rl = jnp.where(free & has_l & (d < 0), (zl - z) / jnp.where(d < 0, d, -1.0), inf)
        ru = jnp.where(free & (d > 0), (zu - z) / jnp.where(d > 0, d, 1.0), inf)
        ratio = jnp.minimum(rl, ru)
        k = jnp.argmin(ratio)
        blocked = ratio[k] < 1.0
        hit_u = ru[k] <= rl[k]
        alpha = jnp.clip(ratio[k], 0.0, 1.0)
        z_step = z + alpha * d
        z_step = jnp.where(has_l, jnp.maximum(z_step, zl), z_step)
        z_step = jnp.minimum(z_step, zu)
        onek = jnp.arange(n + m) == k
        z_step = jnp.where(onek, jnp.where(hit_u, zu, zl), z_step)
        # unblocked: at the least-squares point of the split; free the most promising bound.
        # w = A^T (h - A y) with the residual exactly 0 on rows whose t is free
        res = jnp.where(held_t, G @ x - h - y[n:], 0.0)
        w = jnp.concatenate([-(G.T @ res), res])
        tol = jnp.concatenate([jnp.abs(G).T @ jnp.where(held_t, s, 0.0), s])
        cand = ~free & ~fixed & ((~at_u & has_l & (w > tol)) | (at_u & (w < -tol)))
        score = jnp.where(cand, jnp.abs(w) / colnorm, -1.0)
        j = jnp.argmax(score)
        any_c = score[j] > 0
        onej = jnp.arange(n + m) == j
        z_new = jnp.where(blocked, z_step, y)
        free_new = jnp.where(blocked, free & ~onek, free | (onej & any_c))
        at_u_new = jnp.where(blocked & onek, hit_u, at_u)
        done = ~blocked & ~any_c
        return _Split(z_new, free_new, at_u_new, c.it + 1, done)

    def cond(c: _Split):
        return (c.it < max_iter) & ~c.done

    out = jax.lax.while_loop(cond, body, _Split(z0, jnp.zeros((n + m,), bool), at_u0, jnp.int32(0), jnp.bool_(False)))
    return out.free, out.at_u, out.z, out.done
