"""Small dense SPD solves for the box-QP.

* Array form (one problem, the caller vmaps): ``chol_factor`` / ``chol_apply`` / ``chol_solve``,
  an unrolled Cholesky for ``n <= UNROLL_MAX`` (under ``vmap`` every scalar becomes one vector over
  the batch; a batched LAPACK call per 7x7 matrix is far slower on a CPU), LAPACK above or on
  request (``unroll=False``: a much smaller program, for rarely run code).
* Row form (``rchol`` / ``rchol_solve`` / ``rdot`` / ``rmatvec``): scalar code on Python lists
  whose "scalars" are arrays over the batch, for the fast path (see the note further down).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

UNROLL_MAX = 12


def masked_matrix(A, mask):
    """``A`` on the rows and columns where ``mask`` is True, the identity elsewhere."""
    n = A.shape[-1]
    both = mask[:, None] & mask[None, :]
    return jnp.where(both, A, jnp.eye(n, dtype=A.dtype))


def chol_solve(M, b, unroll=True):
    """Solve ``M x = b`` for a symmetric positive definite ``M`` (``(n, n)``), ``b`` ``(n,)`` or ``(n, k)``."""
    return chol_apply(chol_factor(M, unroll), b)


def chol_factor(M, unroll=True):
    """Cholesky factor of an SPD ``(n, n)`` matrix, in the form ``chol_apply`` takes.

    Pivots are floored at ``eps * M_jj`` (and the smallest normal number), so a matrix that rounding
    made semidefinite gives a finite, regularised answer instead of NaN. ``unroll=False`` (or
    ``n > UNROLL_MAX``): LAPACK, a much smaller program (the rarely run robust path uses it).
    """
    n = M.shape[-1]
    eps = jnp.finfo(M.dtype).eps
    tiny = jnp.finfo(M.dtype).tiny
    if n > UNROLL_MAX or not unroll:
        d = jnp.diagonal(M)
        return jnp.linalg.cholesky(M + jnp.diag(eps * jnp.abs(d) + tiny))
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        s = M[j, j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        floor = eps * jnp.abs(M[j, j]) + tiny
        d = jnp.sqrt(jnp.maximum(s, floor))
        L[j][j] = d
        for i in range(j + 1, n):
            t = M[i, j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / d
    return L


def chol_apply(L, b):
    """Solve with a factor from ``chol_factor``; ``b`` of shape ``(n,)`` or ``(n, k)``."""
    if not isinstance(L, list):
        return jax.scipy.linalg.cho_solve((L, True), b)
    if len(L) == 0:
        return b
    return jnp.stack(rchol_solve(L, b))


# --------------------------------------------------------------------------------------------
# "Row" form, for batches of small problems: a vector is a Python list of arrays (one per
# coordinate, each of the batch shape, batch contiguous), a matrix a list of lists. Every operation
# is elementwise over the batch, so XLA compiles an iteration for the whole batch into a few dozen
# vectorised loops instead of one small LAPACK call per problem. Two rules keep XLA's CPU fusion
# from recomputing whole chains in every consumer (it duplicates "cheap" producers freely):
#   * every entry of the factor and of the triangular solves ends in a division (an "expensive"
#     op, which XLA materialises instead of duplicating), not a multiplication by a reciprocal;
#   * results stay lists; stacking them inside a fused computation (a concatenate) makes the
#     CPU emitter recompute every operand per element, unvectorised. Callers stack only values
#     that are already materialised (loop outputs).


def rdot(a, b):
    """``sum_i a_i b_i`` of two row-form vectors (0 for empty vectors)."""
    out = None
    for x, y in zip(a, b):
        out = x * y if out is None else out + x * y
    return 0.0 if out is None else out


def rmatvec(A, x):
    """``A x`` in row form."""
    return [rdot(row, x) for row in A]


def rmatvec_t(A, y, n):
    """``A^T y`` in row form (``A`` has ``len(y)`` rows of ``n`` entries)."""
    return [rdot([A[j][i] for j in range(len(y))], y) if y else 0.0 for i in range(n)]


def rchol(M):
    """Lower Cholesky factor (list of lists) of an SPD row-form matrix (lower triangle read).

    Pivots floored like ``chol_factor`` (rounding-semidefinite matrices give finite answers).
    """
    n = len(M)
    L = [[None] * n for _ in range(n)]
    for j in range(n):
        s = M[j][j]
        for k in range(j):
            s = s - L[j][k] * L[j][k]
        dt = jnp.result_type(M[j][j])
        floor = jnp.finfo(dt).eps * jnp.abs(M[j][j]) + jnp.finfo(dt).tiny
        d = jnp.sqrt(jnp.maximum(s, floor))
        L[j][j] = d
        for i in range(j + 1, n):
            t = M[i][j]
            for k in range(j):
                t = t - L[i][k] * L[j][k]
            L[i][j] = t / d
    return L


def rchol_solve(L, b):
    """Solve ``L L^T x = b`` with a factor from ``rchol``; ``b`` a row-form vector."""
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
    return x
