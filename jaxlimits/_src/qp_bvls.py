"""Least violation of halfspaces over a box (phase 1 of the infeasible case, ``m >= 2``).

``min_{lower <= x <= upper} 1/2 ||max(G x - h, 0)||^2`` written as a bounded-variable least-squares
problem in ``z = (x, t)``:

    min 1/2 ||G x - t - h||^2   s.t.   lower <= x <= upper,   t <= 0,

(at the optimum ``t = min(G x - h, 0)``, so the residual ``r = G x - t - h = max(G x - h, 0)``).
Solved by the active-set method of Lawson & Hanson / Stark & Parker (BVLS): start with every
variable at a bound; repeatedly free the bound variable whose gradient points most into its box,
solve the least-squares problem of the free variables exactly (normal equations, masked
Cholesky), and step back to the first bound hit if that solution leaves the box. It terminates
finitely (in exact arithmetic) at a minimiser. The residual ``r*`` is unique even when the
minimiser is not (strict convexity of the squared norm in ``r``), so the set of least violation
is ``{x in box : G x <= h + r*}``.

Array form, one problem (the caller vmaps). Only problems that the fast path could not settle go
through here.
"""

from __future__ import annotations

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


def _ls(A, h, free, zb):
    """The free part of ``argmin ||A z - h||`` with the held part fixed at ``zb`` (0 elsewhere)."""
    N = masked_matrix(A.T @ A, free)
    rhs = jnp.where(free, A.T @ (h - A @ zb), 0.0)
    return jnp.where(free, chol_solve(N, rhs, unroll=False), 0.0)


def residual(lower, upper, G, h, free, at_u):
    """``(r*, x)`` of the least-squares problem of a final BVLS split (``free``, ``at_u``).

    Written with ordinary differentiable operations: the derivative of ``r*`` w.r.t. the box and
    the halfspaces (the split held fixed) is that of the least violation.
    """
    A, zl, zu, _ = _system(lower, upper, G)
    zb = jnp.where(free, 0.0, jnp.where(at_u, zu, zl))
    z = _ls(A, h, free, zb) + zb
    return jnp.maximum(A @ z - h, 0.0), z[: G.shape[1]]


def bvls(lower, upper, G, h, max_iter):
    """BVLS for one problem. Returns ``(free, at_u, done)``: the final split of ``(x, t)``."""
    m, n = G.shape
    dt = G.dtype
    eps = jnp.finfo(dt).eps
    A, zl, zu, has_l = _system(lower, upper, G)
    fixed = jnp.concatenate([lower >= upper, jnp.zeros((m,), bool)])
    colnorm = jnp.sqrt(jnp.sum(A * A, axis=0)) + jnp.finfo(dt).tiny
    bscale = 1.0 + jnp.max(jnp.abs(h)) + jnp.sum(jnp.max(jnp.abs(G), axis=0) * jnp.maximum(jnp.abs(lower), jnp.abs(upper)))
    tol = 32.0 * eps * (n + m) * (1.0 + jnp.max(jnp.abs(G))) * bscale
    up0 = jnp.sum(G, axis=0) <= 0  # each x at the bound that lowers the rows on the whole
    at_u0 = jnp.concatenate([up0 & ~(lower >= upper), jnp.ones((m,), bool)])
    z0 = jnp.where(at_u0, zu, zl)
    inf = jnp.asarray(jnp.inf, dt)

    def body(state):
        z, free, at_u, it, _ = state
        zb = jnp.where(free, 0.0, z)
        y = _ls(A, h, free, zb) + zb
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
        # unblocked: at the least-squares point of the split; free the most promising bound
        w = A.T @ (h - A @ y)
        cand = ~free & ~fixed & ((~at_u & has_l & (w > tol)) | (at_u & (w < -tol)))
        score = jnp.where(cand, jnp.abs(w) / colnorm, -1.0)
        j = jnp.argmax(score)
        any_c = score[j] > 0
        onej = jnp.arange(n + m) == j
        z_new = jnp.where(blocked, z_step, y)
        free_new = jnp.where(blocked, free & ~onek, free | (onej & any_c))
        at_u_new = jnp.where(blocked & onek, hit_u, at_u)
        done = ~blocked & ~any_c
        return z_new, free_new, at_u_new, it + 1, done

    def cond(state):
        return (state[3] < max_iter) & ~state[4]

    init = (z0, jnp.zeros((n + m,), bool), at_u0, jnp.int32(0), jnp.bool_(False))
    _, free, at_u, _, done = jax.lax.while_loop(cond, body, init)
    return free, at_u, done
