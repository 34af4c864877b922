"""Small dense SPD solves for the box-QP: an unrolled Cholesky that vectorises well over a batch.

For ``n <= UNROLL_MAX`` the factorisation is written out scalar by scalar; under ``vmap`` every
scalar becomes one vector over the batch, which XLA fuses (a batched LAPACK call per 7x7 matrix is
far slower on a CPU). Larger systems use ``jnp.linalg.cholesky``.
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


def chol_solve(M, b):
    """Solve ``M x = b`` for a symmetric positive definite ``M`` (``(n, n)``), ``b`` ``(n,)`` or ``(n, k)``."""
    return chol_apply(chol_factor(M), b)


def chol_factor(M):
    """Cholesky factor of an SPD ``(n, n)`` matrix, in the form ``chol_apply`` takes.

    Pivots are floored at ``eps * M_jj`` (and the smallest normal number), so a matrix that rounding
    made semidefinite gives a finite, regularised answer instead of NaN.
    """
    n = M.shape[-1]
    eps = jnp.finfo(M.dtype).eps
    tiny = jnp.finfo(M.dtype).tiny
    if n > UNROLL_MAX:
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
    n = len(L)
    if n == 0:
        return b
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
