"""Infeasibility-free inverse kinematics: the sampling time as a decision variable (Suleiman et al.).

Solves, per problem of a batch, the paper's QP (15)/(17) and, with end-effector caps, (18)/(21):

    min_{dq, T}  dq^T Q dq + alpha T^2
    s.t.  J dq = dr                                  (the task, an equality)
          v_min T <= dq <= v_max T                   (joint velocity limits)
          b_min T <= A dq <= b_max T                 (optional extra rate constraints)
          dq_min <= dq <= dq_max                     (optional: joint position limits as bounds on dq)
          |dr_i| <= r_dot_max_i T,  ||dr|| <= r_norm_max T   (optional end-effector caps, eq. 19)
          T >= t_min                                 (the paper's epsilon)

and rounds ``T`` up to a multiple of a fixed control period (Sec. IV, eq. 22) when asked.

How (see ``docs/timescale.md``): with ``Q = diag(w)`` and ``D = diag(w^-1/2)`` the equality is
eliminated exactly. A Householder QR of ``(J D)^T = [Q1 Q2] [R; 0]`` (written out in jnp, so it is
differentiable) gives every solution ``dq = D (Q1 R^-T dr + Q2 z)``, ``z`` free in ``R^(n-m)``, and
the objective becomes ``||R^-T dr||^2 + ||z||^2 + alpha T^2``. What is left is a projection of the
origin onto a polytope in ``(z, T)``: the end-effector caps and ``t_min`` are a lower bound on
``T`` (``dr`` is given), the velocity, rate and position constraints are halfspaces. That is
``jaxlimits.solve_box_qp`` (diagonal metric ``(1, ..., 1, alpha)``, a box that provably does not bind
besides ``T``'s lower bound, the rows): exact to its tolerance, batched, with its implicit
derivative. The equality residual does not depend on the QP's accuracy at all (any ``z`` meets it).

Always feasible when ``dr`` is reachable: ``z = 0`` with ``T`` large enough meets every velocity,
rate and cap constraint. Only position limits can make it infeasible (or a singular ``J``):

* singular ``J`` (``min |R_kk| <= rtol max |R_kk|``, ``rtol = 1e3 eps``): the particular solution
  is the damped least-squares one (Tikhonov, ``mu = (rtol max |R_kk|)^2``), finite;
* position rows that cannot hold: ``solve_box_qp``'s least violation, then ``dq`` is clipped into
  ``[dq_min, dq_max]`` (the limits win) and ``T`` raised to what the clipped ``dq`` needs.

``reached`` is False exactly when the returned motion misses ``dr`` (``||J dq - dr||`` beyond
``100 eps (||J|| ||dq|| + ||dr||)``): the motion is then the best effort above, every limit still
holds, nothing is NaN. Finally ``T`` is raised, if needed, to ``max_i dq_i / v_max_i`` (and the rate
rows), so that the velocity limits hold to rounding whatever the QP's tolerance.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits._src.qp import solve_box_qp
from jaxlimits._src.qp_checks import concrete


class TimeScaleResult(NamedTuple):
    """Result of ``timescale_ik`` / ``fixed_time_ik``; batched like ``dr`` without its last axis.

    dq: ``(..., n)`` joint displacement [rad] (``J dq = dr`` when ``reached``).
    t: ``(...)`` the time the motion takes [s]: the continuous optimum, or rounded up to
      ``steps * t_step`` when ``t_step`` is given (eq. 22). ``dq / t`` is the joint velocity.
    t_opt: ``(...)`` the continuous optimum ``T`` of (17)/(21) [s] (before rounding).
    steps: ``(...)`` int32, ``ceil(t_opt / t_step)`` (``(n - 1) T_s <= T <= n T_s``); 1 without
      ``t_step``.
    reached: ``(...)`` bool, ``J dq = dr`` holds (to ``100 eps`` of the problem's scale).
    residual: ``(...)`` ``||J dq - dr||`` [task units].
    converged: ``(...)`` bool, the QP's KKT conditions hold (``solve_box_qp(...).converged``).
    """

    dq: jax.Array
    t: jax.Array
    t_opt: jax.Array
    steps: jax.Array
    reached: jax.Array
    residual: jax.Array
    converged: jax.Array


def _safe_norm(x, axis=-1):
    """``||x||`` with a finite gradient at ``x = 0`` (double where)."""
    sq = jnp.sum(x * x, axis=axis)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def householder_qr(A):
    """Full QR ``A = Qf [R; 0]`` of one ``(n, m)`` matrix, ``m <= n``, by Householder reflections.

    Written in jnp (not ``jnp.linalg.qr``, whose derivative does not exist for the complete ``Qf``)
    so that it is differentiable; a zero column is skipped (reflection = identity), never NaN.
    Returns ``(Qf (n, n), R (m, m))``; ``Qf[:, m:]`` spans the null space of ``A^T`` when ``A`` has
    full column rank.
    """
    n, m = A.shape
    Qf = jnp.eye(n, dtype=A.dtype)
    idx = jnp.arange(n)
    for k in range(m):
        x = jnp.where(idx >= k, A[:, k], 0.0)
        nx = _safe_norm(x)
        s = jnp.where(x[k] >= 0, 1.0, -1.0)
        v = x + jnp.where(idx == k, s * nx, 0.0)  # v = x + sign(x_k) ||x|| e_k: no cancellation
        nv = _safe_norm(v)
        ok = nv > 0
        u = jnp.where(ok, v / jnp.where(ok, nv, 1.0), 0.0)
        A = A - 2.0 * jnp.outer(u, u @ A)
        Qf = Qf - 2.0 * jnp.outer(Qf @ u, u)
    return Qf, A[:m, :]


def _check_positive(name, value):
    arr = None if value is None else concrete(value)
    if arr is None:
        return
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"timescale_ik: {name} must be finite and > 0, got {arr.tolist()}")


def _check_finite(name, value):
    arr = None if value is None else concrete(value)
    if arr is None:
        return
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"timescale_ik: {name} must be finite, got {arr.tolist()}")


def _negated(value):
    """``-value`` as float64 NumPy when concrete (for a ``<= 0`` check by ``_check_positive``), else None."""
    arr = concrete(value)
    return None if arr is None else -arr


def _prepare(J, dr, v_min, v_max, w, dq_min, dq_max, A, b_min, b_max, t_lo, t_fix, alpha):
    """One problem: the reduced QP in ``y = (z, T) / c`` (``z / c`` alone when ``T`` is fixed).

    Returns ``(lower, upper, G, h, aux)``; ``aux = (c, D, Q2, dq_p)``.
    """
    m, n = J.shape
    dtype = J.dtype
    eps = jnp.finfo(dtype).eps
    D = 1.0 / jnp.sqrt(w)
    Qf, R = householder_qr((J * D[None, :]).T)
    Q1, Q2 = Qf[:, :m], Qf[:, m:]
    diag = jnp.abs(jnp.diagonal(R))
    rtol = 1e3 * eps
    dmax = jnp.max(diag)
    singular = jnp.min(diag) <= rtol * dmax
    # particular solution y = R^-T dr: triangular solve, or damped least squares at a singularity
    R_safe = jnp.where(singular, jnp.eye(m, dtype=dtype), R)
    y_reg = jax.scipy.linalg.solve_triangular(R_safe.T, dr, lower=True)
    mu = (rtol * dmax) ** 2 + jnp.finfo(dtype).tiny
    y_damp = jnp.linalg.solve(R @ R.T + mu * jnp.eye(m, dtype=dtype), R @ dr)
    y = jnp.where(singular, y_damp, y_reg)
    dq_p = D * (Q1 @ y)
    DQ2 = D[:, None] * Q2
    fixed = t_fix is not None

    # rows in (z, T) (in z alone for a fixed T): velocity, rate (A), position
    def row(Gz, gT, rhs):
        return (Gz, rhs - gT * t_fix) if fixed else (jnp.concatenate([Gz, gT[:, None]], 1), rhs)

    parts = [row(DQ2, -v_max, -dq_p), row(-DQ2, v_min, dq_p)]
    if A is not None:
        ADQ2, Adq = A @ DQ2, A @ dq_p
        parts += [row(ADQ2, -b_max, -Adq), row(-ADQ2, b_min, Adq)]
    if dq_min is not None:
        zn = jnp.zeros((n,), dtype)
        parts += [row(DQ2, zn, dq_max - dq_p), row(-DQ2, zn, dq_p - dq_min)]
    G = jnp.concatenate([g for g, _ in parts], 0)
    h = jnp.concatenate([r for _, r in parts], 0)

    # a box on (z, T) that cannot bind at the optimum (besides T >= t_lo): from a feasible point
    # (z = 0 when dq_p meets the position bounds, else any dq of the position box) an objective
    # bound F, then alpha T*^2 + ||z*||^2 <= F
    big = jnp.abs(dq_p)
    if dq_min is not None:
        inside = jnp.all((dq_p >= dq_min) & (dq_p <= dq_max))
        big = jnp.where(inside, big, jnp.maximum(big, jnp.maximum(jnp.abs(dq_min), jnp.abs(dq_max))))
    vcap = jnp.minimum(v_max, -v_min)
    if fixed:
        t_lo = t_fix
    t_f = jnp.maximum(t_lo, jnp.max(big / vcap))
    if A is not None:
        bcap = jnp.minimum(b_max, -b_min)
        t_f = jnp.maximum(t_f, jnp.max(jnp.abs(A) @ big / bcap))
    F = jnp.sum((big / D) ** 2) + alpha * t_f**2
    t_hi = t_lo + 2.0 * jnp.sqrt(F / alpha) + 2.0 * t_f
    z_hi = 2.0 * jnp.sqrt(F)
    if fixed:  # |D Q2 z| <= v T + |dq_p| on the velocity rows' feasible set (and near it)
        z_hi = 2.0 * _safe_norm(jnp.maximum(v_max, -v_min) * t_fix + jnp.abs(dq_p)) / jnp.min(D)
    # scale to O(1) numbers: T / c ~ 1, z / c ~ a velocity (the QP's tolerances are absolute)
    t_c = t_fix if fixed else jnp.maximum(t_lo, jnp.max(jnp.abs(dq_p) / vcap))  # T of the point z = 0
    c = jax.lax.stop_gradient(jnp.maximum(t_c, jnp.finfo(dtype).tiny))
    d = n - m
    if fixed:
        lower, upper = jnp.full((d,), -z_hi, dtype) / c, jnp.full((d,), z_hi, dtype) / c
    else:
        lower = jnp.concatenate([jnp.full((d,), -z_hi, dtype), jnp.reshape(t_lo, (1,))]) / c
        upper = jnp.concatenate([jnp.full((d,), z_hi, dtype), jnp.reshape(t_hi, (1,))]) / c
    h = h / c
    # rows that no point of the box can reach are capped just above the box's reach: the same
    # problem, and solve_box_qp's least-violation stage misjudged rows with far-away h as infeasible
    reach = jnp.sum(jnp.maximum(G * lower[None, :], G * upper[None, :]), axis=1)
    h = jnp.minimum(h, reach + 1.0 + jnp.abs(reach))
    return lower, upper, G, h, (c, D, Q2, dq_p)


def _finish(y, J, dr, v_min, v_max, dq_min, dq_max, A, b_min, b_max, t_lo, t_fix, aux):
    c, D, Q2, dq_p = aux
    m, n = J.shape
    dtype = J.dtype
    eps = jnp.finfo(dtype).eps
    z = y[: n - m] * c
    dq = dq_p + D * (Q2 @ z)
    if dq_min is not None:
        dq = jnp.clip(dq, dq_min, dq_max)
    if t_fix is None:
        T = y[n - m] * c
        # T's lower bound, where it binds, exactly (the QP returns it up to the rounding of the scaling)
        T = jnp.where(T <= t_lo * (1.0 + 64.0 * eps), t_lo, T)
        # velocity (and rate) rows exactly, whatever the QP tolerance: raise T to what dq needs
        need = jnp.maximum(jnp.max(dq / v_max), jnp.max(dq / v_min))
        if A is not None:
            Adq = A @ dq
            need = jnp.maximum(need, jnp.maximum(jnp.max(Adq / b_max), jnp.max(Adq / b_min)))
        T = jnp.maximum(jnp.maximum(T, need), t_lo)
    else:
        T = jnp.asarray(t_fix, dtype)
    res = _safe_norm(J @ dq - dr)
    scale = _safe_norm(J.reshape(-1)) * _safe_norm(dq) + _safe_norm(dr) + jnp.finfo(dtype).tiny
    reached = res <= 100.0 * eps * scale
    return dq, T, reached, res


def _as(x, dtype, name):
    if x is None:
        return None
    _check_finite(name, x)
    return jnp.asarray(x, dtype)


@functools.partial(jax.jit, static_argnames=("max_iter",))
def _core(J, dr, v_min, v_max, w, dq_min, dq_max, A, b_min, b_max, t_lo, t_fix, alpha, max_iter):
    """The whole batch (flat: ``J (B, m, n)``), one compiled program; ``None`` arguments are absent."""
    B, m, n = J.shape
    dtype = J.dtype
    pos = dq_min is not None
    if not pos:
        dq_min = dq_max = jnp.zeros((B, 0), dtype)

    def prep(Ji, dri, loi, hii, tli):
        return _prepare(
            Ji, dri, v_min, v_max, w, loi if pos else None, hii if pos else None, A, b_min, b_max, tli, t_fix, alpha
        )

    lower, upper, G, h, aux = jax.vmap(prep)(J, dr, dq_min, dq_max, t_lo)
    if t_fix is None:
        metric = jnp.concatenate([jnp.ones((n - m,), dtype), jnp.reshape(alpha, (1,))])
    else:
        metric = jnp.ones((n - m,), dtype)
    if lower.shape[-1]:
        qp = solve_box_qp(jnp.zeros_like(lower), lower, upper, metric, G=G, h=h, max_iter=max_iter)
        y, conv = qp.x, qp.converged
    else:  # n == m with a fixed T: nothing to choose
        y, conv = lower, jnp.ones((B,), bool)

    def fin(yi, Ji, dri, loi, hii, tli, auxi):
        return _finish(
            yi, Ji, dri, v_min, v_max, loi if pos else None, hii if pos else None, A, b_min, b_max, tli, t_fix, auxi
        )

    dq, T, reached, res = jax.vmap(fin)(y, J, dr, dq_min, dq_max, t_lo, aux)
    return TimeScaleResult(dq, T, T, jnp.ones(T.shape, jnp.int32), reached, res, conv)


def _round(out, t_step):
    """Sec. IV, eq. 22: ``steps = ceil(T / T_s)``, ``t = steps T_s`` (derivative 0 w.r.t. ``T``)."""
    steps = jnp.maximum(jnp.ceil(jax.lax.stop_gradient(out.t_opt) / t_step), 1.0)
    return out._replace(t=steps * t_step, steps=steps.astype(jnp.int32))


def _solve(
    J,
    dr,
    v_max,
    v_min,
    t_min,
    t_fix,
    alpha,
    weights,
    r_dot_max,
    r_norm_max,
    dq_min,
    dq_max,
    A,
    b_min,
    b_max,
    t_step,
    max_iter,
    fname,
):
    J0 = jnp.asarray(J)
    dtype = jnp.promote_types(J0.dtype, jnp.float32)
    J = _as(J, dtype, "J")
    dr = _as(dr, dtype, "dr")
    if J.ndim < 2 or dr.ndim < 1 or J.shape[-2] != dr.shape[-1]:
        raise ValueError(f"{fname}: J must have shape (..., m, n) and dr (..., m), got J {J.shape} and dr {dr.shape}")
    m, n = J.shape[-2:]
    if m > n or m < 1:
        raise ValueError(f"{fname}: need 1 <= m <= n (task dimension at most the joint count), got J {J.shape}")
    _check_positive("v_max", v_max)
    v_max = jnp.broadcast_to(_as(v_max, dtype, "v_max"), (n,))
    if v_min is None:
        v_min = -v_max
    else:
        _check_positive("-v_min", _negated(v_min))
        v_min = jnp.broadcast_to(_as(v_min, dtype, "v_min"), (n,))
    if t_fix is None:
        _check_positive("t_min", t_min)
        _check_positive("alpha", alpha)
    else:
        _check_positive("t", t_fix)
    _check_positive("weights", weights)
    _check_positive("r_dot_max", r_dot_max)
    _check_positive("r_norm_max", r_norm_max)
    _check_positive("t_step", t_step)
    w = jnp.ones((n,), dtype) if weights is None else jnp.broadcast_to(_as(weights, dtype, "weights"), (n,))
    alpha = jnp.asarray(1.0 if alpha is None else alpha, dtype)
    if (dq_min is None) != (dq_max is None):
        raise ValueError(f"{fname}: give both dq_min and dq_max or neither")
    if dq_min is not None:
        lo_n, hi_n = concrete(dq_min), concrete(dq_max)
        if lo_n is not None and hi_n is not None:
            if np.any(lo_n > 0) or np.any(hi_n < 0):
                raise ValueError(
                    f"{fname}: need dq_min <= 0 <= dq_max (the current position inside its limits), "
                    f"got dq_min={lo_n.tolist()}, dq_max={hi_n.tolist()}"
                )
        dq_min = _as(dq_min, dtype, "dq_min")
        dq_max = _as(dq_max, dtype, "dq_max")
    if A is not None:
        if b_min is None or b_max is None:
            raise ValueError(f"{fname}: A needs b_min and b_max")
        A = _as(A, dtype, "A")
        if A.ndim != 2 or A.shape[1] != n:
            raise ValueError(f"{fname}: A must have shape (k, {n}), got {A.shape}")
        _check_positive("b_max", b_max)
        _check_positive("-b_min", _negated(b_min))
        b_min = jnp.broadcast_to(_as(b_min, dtype, "b_min"), (A.shape[0],))
        b_max = jnp.broadcast_to(_as(b_max, dtype, "b_max"), (A.shape[0],))
    if max_iter is not None and (
        isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1
    ):
        raise ValueError(f"{fname}: max_iter must be an integer >= 1, got {max_iter!r}")

    batch = jnp.broadcast_shapes(
        J.shape[:-2], dr.shape[:-1], *([] if dq_min is None else [dq_min.shape[:-1], dq_max.shape[:-1]])
    )
    B = int(np.prod(batch)) if batch else 1
    Jb = jnp.broadcast_to(J, batch + (m, n)).reshape(B, m, n)
    drb = jnp.broadcast_to(dr, batch + (m,)).reshape(B, m)
    lo_b = hi_b = None
    if dq_min is not None:
        lo_b = jnp.broadcast_to(dq_min, batch + (n,)).reshape(B, n)
        hi_b = jnp.broadcast_to(dq_max, batch + (n,)).reshape(B, n)

    # lower bound on T: t_min and the end-effector caps (eq. 19 per component, or a norm cap)
    t_lo = jnp.full((B,), jnp.asarray(t_min if t_fix is None else 0.0, dtype))
    if t_fix is None:
        if r_dot_max is not None:
            rd = jnp.broadcast_to(_as(r_dot_max, dtype, "r_dot_max"), (m,))
            t_lo = jnp.maximum(t_lo, jnp.max(jnp.abs(drb) / rd[None, :], axis=-1))
        if r_norm_max is not None:
            t_lo = jnp.maximum(t_lo, _safe_norm(drb) / jnp.asarray(r_norm_max, dtype))
    tf = None if t_fix is None else jnp.asarray(t_fix, dtype)
    ts = None if (t_step is None or t_fix is not None) else jnp.asarray(t_step, dtype)
    out = _core(
        Jb,
        drb,
        v_min,
        v_max,
        w,
        lo_b,
        hi_b,
        A,
        b_min,
        b_max,
        t_lo,
        tf,
        alpha,
        None if max_iter is None else int(max_iter),
    )
    if ts is not None:
        out = _round(out, ts)
    return jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), out)


def timescale_ik(
    J,
    dr,
    v_max,
    *,
    v_min=None,
    t_min=1e-3,
    alpha=1.0,
    weights=None,
    r_dot_max=None,
    r_norm_max=None,
    dq_min=None,
    dq_max=None,
    A=None,
    b_min=None,
    b_max=None,
    t_step=None,
    max_iter=None,
) -> TimeScaleResult:
    """Time-scaled IK step: ``(dq, T)`` solving the paper's QP (17) (and (21) with end-effector caps).

    ``min dq^T Q dq + alpha T^2`` s.t. ``J dq = dr``, ``v_min T <= dq <= v_max T``,
    ``b_min T <= A dq <= b_max T``, ``dq_min <= dq <= dq_max``, ``|dr_i| <= r_dot_max_i T``,
    ``||dr|| <= r_norm_max T``, ``T >= t_min``; see the module docstring for the method.

    Args:
      J: ``(..., m, n)`` task Jacobian, ``m <= n`` (e.g. the end-effector's linear rows [m/rad]).
      dr: ``(..., m)`` the task displacement to make (eq. 14) [m, rad].
      v_max: ``(n,)`` or scalar, joint velocity limit [rad/s], > 0. ``v_min`` (default ``-v_max``) < 0.
      t_min: the paper's epsilon [s], > 0: the shortest step (in an env: its control period).
      alpha: weight of ``T^2`` [(rad/s)^2], > 0: large values favour the shortest ``T`` (fastest
        motion), small ones the smallest weighted ``||dq||``.
      weights: ``(n,)`` positive diagonal of ``Q`` (default ones).
      r_dot_max: ``(m,)`` or scalar per-component end-effector speed caps (eq. 19) [m/s, rad/s].
      r_norm_max: scalar cap on ``||dr|| / T`` (a linear-speed cap when ``dr`` is a position).
      dq_min, dq_max: ``(..., n)`` bounds on ``dq`` (joint position limits: ``q_min - q``,
        ``q_max - q``), ``dq_min <= 0 <= dq_max``.
      A, b_min, b_max: ``(k, n)``, ``(k,)``, ``(k,)``: extra rate constraints
        ``b_min T <= A dq <= b_max T`` (``b_min < 0 < b_max``).
      t_step: the control period ``T_s`` [s]: ``t`` is rounded up to ``ceil(T / T_s) T_s`` (eq. 22).
      max_iter: passed to ``solve_box_qp``.

    Returns: ``TimeScaleResult``. Jittable, vmappable, differentiable (implicit derivative of the
    QP; the rounding of eq. 22 has derivative 0 w.r.t. ``T``). float32 and float64.

    Raises (eagerly, concrete inputs): ``ValueError`` naming the field for bad shapes, ``m > n``,
    non-positive ``v_max``/``t_min``/``alpha``/``weights``/caps/``t_step``, non-finite values,
    ``dq_min > 0`` or ``dq_max < 0``.
    """
    return _solve(
        J,
        dr,
        v_max,
        v_min,
        t_min,
        None,
        alpha,
        weights,
        r_dot_max,
        r_norm_max,
        dq_min,
        dq_max,
        A,
        b_min,
        b_max,
        t_step,
        max_iter,
        "timescale_ik",
    )


def fixed_time_ik(
    J,
    dr,
    t,
    v_max,
    *,
    v_min=None,
    weights=None,
    dq_min=None,
    dq_max=None,
    A=None,
    b_min=None,
    b_max=None,
    max_iter=None,
) -> TimeScaleResult:
    """Conventional velocity IK (5) with a fixed sampling time ``t`` [s]: the baseline.

    ``min dq^T Q dq`` s.t. ``J dq = dr`` first, then the inequalities (``v_min t <= dq <= v_max t``
    and the optional rows of ``timescale_ik``) with the least violation when they cannot hold
    (the paper: "the solver tries first to satisfy the equality constraints"). ``reached`` as in
    ``timescale_ik``; ``dq / t`` may exceed the velocity limits (check it: that is the point).
    """
    return _solve(
        J,
        dr,
        v_max,
        v_min,
        None,
        t,
        None,
        weights,
        None,
        None,
        dq_min,
        dq_max,
        A,
        b_min,
        b_max,
        None,
        max_iter,
        "fixed_time_ik",
    )


__all__ = ["TimeScaleResult", "fixed_time_ik", "householder_qr", "timescale_ik"]
