"""The linear algebra of the box-QP: SPD solves, the KKT system of an active set, tolerances.

Layout: *problem axes first, batch axes last*. A vector of one problem is ``(k, *batch)``, a
matrix ``(p, q, *batch)``, a per-problem scalar ``(*batch)``; ``batch`` is ``()`` for one problem
(the robust path vmaps that) and ``(B,)`` for the fast path and the derivative, which call the same
functions on the whole batch. Every scalar of the unrolled code below is then one contiguous vector
over the batch and XLA runs it as a vectorised loop (a batched LAPACK call per 7 x 7 matrix is far
slower on a CPU; ``vmap`` with the batch last would not keep it last: its rules move batch axes to
the front around concatenations).

* ``chol_factor`` / ``chol_apply`` / ``chol_solve``: Cholesky, unrolled for ``n <= UNROLL_MAX``,
  LAPACK above or on request (``unroll=False``: a much smaller program, for rarely run code). The
  factor is an ``(n, n, *batch)`` lower-triangular array either way. Every entry of the unrolled
  factor and of the triangular solves ends in a division: XLA's CPU fusion materialises a division
  instead of recomputing it in every consumer (it duplicates "cheap" producers freely, which turns
  the factor's DAG into a tree).
* ``kkt_solve``: the equality-constrained QP of an active set (masked Cholesky of ``W_FF`` and an
  ``m x m`` Schur complement for the held rows).
* ``active_free``: which bounds a KKT point holds (the active set of the derivative).
* ``scales``: the absolute tolerances that rounding sets for a problem.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

UNROLL_MAX = 12


def eye_like(A):
    """The identity ``(n, n, 1, ...)`` that broadcasts against ``A`` ``(n, n, *batch)``."""
    n = A.shape[0]
    return jnp.eye(n, dtype=A.dtype).reshape((n, n) + (1,) * (A.ndim - 2))


def diagonal(A):
    """The diagonal ``(n, *batch)`` of ``A`` ``(n, n, *batch)``."""
    return jnp.moveaxis(jnp.diagonal(A, axis1=0, axis2=1), -1, 0)


def masked_matrix(A, mask):
    """``A`` ``(n, n, *batch)`` on the rows and columns where ``mask`` ``(n, *batch)`` holds, the
    identity elsewhere."""
    return jnp.where(mask[:, None] & mask[None, :], A, eye_like(A))


def matvec(A, x):
    """``A x`` for ``A`` ``(p, q, *batch)`` and ``x`` ``(q, *batch)``: ``(p, *batch)``."""
    return jnp.sum(A * x[None], axis=1)


def matvec_t(A, y):
    """``A^T y`` for ``A`` ``(p, q, *batch)`` and ``y`` ``(p, *batch)``: ``(q, *batch)`` (zeros when ``p == 0``)."""
    return jnp.sum(A * y[:, None], axis=0)


def _unrolled(n, unroll):
    return unroll and n <= UNROLL_MAX


def _lapack(f, L, *args):
    """``f`` on one problem's ``(n, n)`` matrices, mapped over the trailing batch axes of ``L``."""
    nb = L.ndim - 2
    if nb == 0:
        return f(L, *args)
    batch = L.shape[2:]
    flat = [a.reshape(a.shape[: a.ndim - nb] + (-1,)) for a in (L,) + args]
    out = jax.vmap(f, in_axes=-1, out_axes=-1)(*flat)
    return out.reshape(out.shape[:-1] + batch)


def _factor_rows(M):
    """The unrolled lower Cholesky factor of ``M`` as a list of rows of ``(*batch)`` entries (``chol_factor``)."""
    n = M.shape[0]
    eps = jnp.finfo(M.dtype).eps
    tiny = jnp.finfo(M.dtype).tiny
    zero = jnp.zeros(M.shape[2:], M.dtype)
    L = [[zero] * n for _ in range(n)]
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        d = jnp.sqrt(jnp.maximum(s, eps * jnp.abs(M[j, j]) + tiny))
        L[j][j] = d
        for i in range(j + 1, n):
            t = M[i, j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / d
    return L


def _solve_rows(L, b):
    """Forward and back substitution with a factor read entry by entry (``L[i][k]``: the list of rows
    of ``_factor_rows``, or a stacked factor); ``b`` ``(n, ...)``. Solving from the list avoids
    slicing a stacked factor back apart, which XLA does not fold away (a solve then costs ~25 % more)."""
    n = len(L)
    y = [None] * n
    for i in range(n):
        t = b[i]
        for k in range(i):
            t = t - L[i][k] * y[k]
        y[i] = t / L[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        t = y[i]
        for k in range(i + 1, n):
            t = t - L[k][i] * x[k]
        x[i] = t / L[i][i]
    return jnp.stack(x)


def _stack(rows):
    return jnp.stack([jnp.stack(row) for row in rows])


def chol_factor(M, unroll=True):
    """Lower Cholesky factor ``(n, n, *batch)`` of a symmetric positive definite ``M`` ``(n, n, *batch)``.

    Pivots are floored at ``eps * M_jj`` (and the smallest normal number), so a matrix that rounding
    made semidefinite gives a finite, regularised answer instead of NaN. ``unroll=False`` (or
    ``n > UNROLL_MAX``): LAPACK, a much smaller program (the rarely run robust path uses it).
    """
    n = M.shape[0]
    if _unrolled(n, unroll):
        return _stack(_factor_rows(M))
    eps = jnp.finfo(M.dtype).eps
    tiny = jnp.finfo(M.dtype).tiny

    def lapack(A):
        return jnp.linalg.cholesky(A + jnp.diag(eps * jnp.abs(jnp.diagonal(A)) + tiny))

    return _lapack(lapack, M)


def chol_apply(L, b, unroll=True):
    """Solve ``L L^T x = b`` with ``L`` ``(n, n, *batch)`` from ``chol_factor`` (same ``unroll``).

    ``b``: ``(n, *batch)``; for one problem (``batch == ()``) also ``(n, k)``, ``k`` right-hand sides.
    """
    if not _unrolled(L.shape[0], unroll):
        return _lapack(lambda c, v: jax.scipy.linalg.cho_solve((c, True), v), L, b)
    return _solve_rows(L, b)


def chol_solve(M, b, unroll=True):
    """Solve ``M x = b`` for a symmetric positive definite ``M`` (shapes as in ``chol_apply``)."""
    if _unrolled(M.shape[0], unroll):
        return _solve_rows(_factor_rows(M), b)
    return chol_apply(chol_factor(M, unroll), b, unroll)


def kkt_solve(W, G, free, rows, r, s, unroll=True):
    """Solve the equality-constrained KKT system of an active set.

    Unknowns ``y`` ``(n, *batch)`` (on ``free`` coordinates; 0 elsewhere) and ``lam`` ``(m, *batch)``
    (on active ``rows``; 0 elsewhere) with ``W_FF y_F + G_RF^T lam_R = r_F`` and ``G_RF y_F = s_R``
    (Schur complement on the small ``m x m`` block, regularised by a few ulps so that dependent
    rows stay finite, plus one refinement step). ``W`` ``(n, n, *batch)``, ``G`` ``(m, n, *batch)``.
    Returns ``(y, lam)``.
    """
    m = G.shape[0]
    M = masked_matrix(W, free)
    if _unrolled(W.shape[0], unroll):
        factor = _factor_rows(M)

        def apply(b):
            return _solve_rows(factor, b)

        def apply_columns(b):  # (n, k, *batch): k right-hand sides at once, each entry as in ``apply``
            return _solve_rows([[e[None] for e in row] for row in factor], b)
    else:
        factor = chol_factor(M, unroll)

        def apply(b):
            return chol_apply(factor, b, unroll)

        apply_columns = apply

    rf = jnp.where(free, r, 0.0)
    if m == 0:
        return jnp.where(free, apply(rf), 0.0), jnp.zeros((0,) + W.shape[2:], W.dtype)
    GF = jnp.where(free[None], G, 0.0)
    eps = jnp.finfo(W.dtype).eps
    # a row whose free part vanishes is fixed by the box alone: nothing to solve for it
    rows = rows & (jnp.sum(GF * GF, axis=1) > eps * eps * jnp.sum(G * G, axis=1))
    GF = jnp.where(rows[:, None], GF, 0.0)
    y = apply(rf)  # apart from Z: y is linear in tangents, Z is not
    # (n, m, *batch); the m solves as one (unrolled one by one, they were most of the program)
    Z = apply_columns(jnp.swapaxes(GF, 0, 1))
    S = jnp.sum(GF[:, :, None] * Z[None], axis=1)
    reg = 1e2 * eps * (jnp.max(jnp.abs(diagonal(S)), axis=0) + jnp.finfo(W.dtype).tiny)
    S = masked_matrix(S, rows) + reg[None, None] * eye_like(S)
    Sf = chol_factor(S, unroll)
    lam = jnp.where(rows, chol_apply(Sf, jnp.where(rows, matvec(GF, y) - s, 0.0), unroll), 0.0)
    # one step of iterative refinement on the rows: undoes the regularisation where the held rows
    # are nearly dependent (large multipliers), so that they hold to rounding
    e = jnp.where(rows, matvec(GF, y - matvec(Z, lam)) - s, 0.0)
    lam = lam + jnp.where(rows, chol_apply(Sf, e, unroll), 0.0)
    x = jnp.where(free, y - matvec(Z, lam), 0.0)
    return x, lam


def active_free(x, lower, upper, g, tol_g):
    """The coordinates free at a KKT point ``x`` ``(n, *batch)`` with gradient
    ``g = W (x - x_des) + G^T lam``, for the gradient tolerance ``tol_g`` ``(*batch)``.

    A bound is held only by a multiplier larger than ``tol_g`` (a weakly active bound, the dense
    analogue of a tie, is free), and a flat coordinate ``lower == upper`` is never free. ``(n,
    *batch)`` bool; the active set of the implicit derivative.
    """
    hold_l = (x <= lower) & (g > tol_g[None])
    hold_u = (x >= upper) & (g < -tol_g[None])
    return ~(hold_l | hold_u) & (lower < upper)


def scales(x_des, lower, upper, W, G, h):
    """Absolute tolerances ``(tol_x, tol_g, tol_h)`` of a problem, a few dozen ulps of their scales:
    in units of x and of the gradient (``(*batch)``), and of each halfspace row (``(m, *batch)``)."""
    eps = jnp.finfo(x_des.dtype).eps
    clipped = jnp.clip(x_des, lower, upper)
    sx = 1.0 + jnp.max(jnp.abs(clipped), axis=0) + jnp.max(jnp.abs(x_des - clipped), axis=0)
    sw = jnp.max(jnp.abs(W), axis=(0, 1))
    n = x_des.shape[0]
    tol_x = 32.0 * eps * sx
    tol_g = 4.0 * eps * sw * sx * n
    gnorm = jnp.max(jnp.abs(G), axis=1) if G.shape[0] else jnp.zeros(h.shape, x_des.dtype)
    tol_h = 32.0 * eps * (gnorm * sx[None] * n + jnp.abs(h))
    return tol_x, tol_g, tol_h
