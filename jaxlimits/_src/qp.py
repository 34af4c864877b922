"""The differentiable box-QP projection (with optional halfspaces); see ``docs/qp.md``.

Solves, per problem of a batch,

    min_x  1/2 (x - x_des)^T W (x - x_des)   s.t.   lower <= x <= upper,   G x <= h.

* ``metric=None`` or a 1-D positive diagonal, no halfspaces: the exact clip, with a custom JVP
  (identity on free coordinates, zero on active ones; the tie rule is in ``_clip``).
* dense SPD metric and/or halfspaces: a primal active-set method (``_active_set_solve``) whose
  every iteration solves the working set's equality-constrained QP exactly (masked Cholesky plus
  an ``m x m`` Schur complement), bounded iterations under ``lax.while_loop``; implicit
  differentiation through the KKT system of the final active set (``jax.custom_jvp``: forward and
  reverse mode).
* The returned ``x`` is always clipped to the box at the end: the box holds exactly whatever the
  iteration count did.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits._src.qp_checks import check_inputs
from jaxlimits._src.qp_linalg import chol_apply, chol_factor, chol_solve, masked_matrix

GRADIENTS = ("exact", "straight_through")


class BoxQPResult(NamedTuple):
    """Result of ``solve_box_qp``; every field is batched like ``x_des`` without its last axis.

    x: ``(..., n)``, the projection; ``lower <= x <= upper`` holds exactly, always.
    converged: ``(...)`` bool, the KKT conditions hold to the solver tolerance (always True for
      the clip).
    iterations: ``(...)`` int32, active-set iterations spent (0 for the clip).
    infeasible: ``(...)`` bool, some halfspace cannot hold together with the box; the rows that
      cannot are met with the least violation (see ``solve_box_qp``). False without halfspaces.
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


def _kkt_solve(W, G, free, rows, r, s):
    """Solve the equality-constrained KKT system of an active set.

    Unknowns ``y`` (on ``free`` coordinates; 0 elsewhere) and ``lam`` (on active ``rows``; 0
    elsewhere) with ``W_FF y_F + G_RF^T lam_R = r_F`` and ``G_RF y_F = s_R`` (Schur complement on
    the small ``m x m`` block, regularised by a few ulps so that dependent rows stay finite).
    """
    n, m = W.shape[0], G.shape[0]
    M = masked_matrix(W, free)
    rf = jnp.where(free, r, 0.0)
    if m == 0:
        return jnp.where(free, chol_solve(M, rf), 0.0), jnp.zeros((0,), W.dtype)
    GF = jnp.where(free[None, :], G, 0.0)
    eps = jnp.finfo(W.dtype).eps
    # a row whose free part vanishes is fixed by the box alone: nothing to solve for it
    rows = rows & (jnp.sum(GF * GF, axis=1) > eps * eps * jnp.sum(G * G, axis=1))
    GF = jnp.where(rows[:, None], GF, 0.0)
    fac = chol_factor(M)
    y, Z = chol_apply(fac, rf), chol_apply(fac, GF.T)  # apart: y is linear in tangents, Z is not
    S = GF @ Z
    reg = 1e2 * eps * (jnp.max(jnp.abs(jnp.diagonal(S))) + jnp.finfo(W.dtype).tiny)
    S = masked_matrix(S, rows) + reg * jnp.eye(m, dtype=W.dtype)
    lam = jnp.where(rows, chol_solve(S, jnp.where(rows, GF @ y - s, 0.0)), 0.0)
    x = jnp.where(free, y - Z @ lam, 0.0)
    return x, lam


def _active_sets(x, x_des, lower, upper, W, G, lam, tol_g):
    """Box coordinates held by a strictly positive multiplier (ties count as free)."""
    g = W @ (x - x_des) + G.T @ lam
    hold_l = (x <= lower) & (g > tol_g)
    hold_u = (x >= upper) & (g < -tol_g)
    free = ~(hold_l | hold_u) & (lower < upper)
    return free, g


def _kkt_ok(x, x_des, lower, upper, W, G, h, lam, tols):
    """The KKT conditions hold at ``(x, lam)`` to 30 times the tolerances ``tols`` (rounding)."""
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
    primal_h = jnp.all(gx <= tol_h)
    dual_h = jnp.all(lam >= 0.0) & jnp.all((lam == 0.0) | (jnp.abs(gx) <= tol_h))
    return inside & stat & primal_h & dual_h


def _feasible_start(y, lower, upper, G, h, passes: int = 2):
    """A box point meeting the rows, from ``y``: move towards the face minimising each violated row.

    The face ``argmin_box G_j x`` meets row ``j`` (rows that cannot are relaxed beforehand), and
    ``y + beta (face - y)`` with ``beta = (G_j y - h_j) / (G_j y - G_j face)`` meets it with
    equality inside the box. Exact for one row; for several rows a second pass usually suffices
    (not guaranteed: then the active-set loop starts from an infeasible point and may flag
    ``converged=False``).
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


def _active_set_solve(x_des, lower, upper, W, G, h, max_iter, tols):
    """Primal active-set method on the box and the rows (working set: held bounds and rows).

    Each iteration solves the equality-constrained QP of the working set exactly (``_kkt_solve``)
    and steps towards its solution ``z``: all the way if no constraint outside the working set
    blocks (then the multiplier of most negative sign, if any, is released), else up to the first
    blocking constraint, which joins the working set. From a feasible point the objective never
    increases and no working set repeats, so it terminates (finitely, in exact arithmetic). The
    start is ``clip(x_des)`` with the clipped bounds and the violated rows held; a violated row is
    met with equality after the first full step, so the iterate is feasible from then on.
    """
    tol_x, tol_g, tol_h = tols
    n, m = W.shape[0], G.shape[0]
    flat = lower >= upper
    y0 = _feasible_start(jnp.clip(x_des, lower, upper), lower, upper, G, h)
    held_l0 = (y0 <= lower) & ((x_des < lower) | flat)
    held_u0 = (y0 >= upper) & (x_des > upper) & ~flat
    rows0 = (G @ y0 - h >= 0) if m else jnp.zeros((0,), bool)
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
        # blocking box bounds (free coordinates only) and rows outside the working set
        ratio_l = jnp.where(free & (d < 0), (lower - y) / jnp.where(d < 0, d, -1.0), jnp.inf)
        ratio_u = jnp.where(free & (d > 0), (upper - y) / jnp.where(d > 0, d, 1.0), jnp.inf)
        ratios = [ratio_l, ratio_u]
        if m:
            gd = G @ d
            slack = jnp.maximum(h - G @ y, 0.0)
            ratios.append(jnp.where(~rows & (gd > 0), slack / jnp.where(gd > 0, gd, 1.0), jnp.inf))
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
        cand = jnp.concatenate([mult, jnp.full((n,), jnp.inf, W.dtype), jnp.where(rows, lam_z * gn, jnp.inf)])
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


def _solve_one(x_des, lower, upper, W, G, h, max_iter):
    """One problem: returns ``(x, lam, converged, iterations)``."""
    tols = _scales(x_des, lower, upper, W, G, h)
    x, lam, done, it = _active_set_solve(x_des, lower, upper, W, G, h, max_iter, tols)
    x = jnp.clip(x, lower, upper)
    return x, lam, done & _kkt_ok(x, x_des, lower, upper, W, G, h, lam, tols), it


def _tangent(x, lam, primals, tangents, tol_g):
    """Implicit derivative: differentiate the KKT conditions of the final active set."""
    x_des, lower, upper, W, G, h = primals
    dxd, dl, du, dW, dG, dh = tangents
    free, _ = _active_sets(x, x_des, lower, upper, W, G, lam, tol_g)
    at_l = x <= 0.5 * (lower + upper)
    dxa = jnp.where(free, 0.0, jnp.where(at_l, dl, du))
    r = W @ dxd - dW @ (x - x_des) - dG.T @ lam - W @ dxa
    rows = lam > 0
    s = dh - dG @ x - G @ dxa
    dxf, dlam = _kkt_solve(W, G, free, rows, r, s)
    return dxf + dxa, dlam


def _make_core(max_iter: int):
    @jax.custom_jvp
    def core(x_des, lower, upper, W, G, h):
        x, lam, ok, it = _solve_one(x_des, lower, upper, W, G, h, max_iter)
        return x, lam, ok.astype(x.dtype), it.astype(x.dtype)

    @core.defjvp
    def core_jvp(primals, tangents):
        out = core(*primals)
        x, lam = out[0], out[1]
        tols = _scales(*primals)
        dx, dlam = _tangent(x, lam, primals, tangents, tols[1])
        return out, (dx, dlam, jnp.zeros_like(out[2]), jnp.zeros_like(out[3]))

    return core


_CORES: dict = {}


def _core(max_iter: int):
    key = max_iter
    if key not in _CORES:
        _CORES[key] = _make_core(max_iter)
    return _CORES[key]


def _pin_infeasible_rows(lower, upper, G, h):
    """Rows that no box point satisfies: pin their coordinates at the minimising bounds, drop them.

    ``min_{lower<=x<=upper} G_j x = sum_i min(G_ji lower_i, G_ji upper_i)`` is attained exactly on
    the face ``x_i = lower_i`` (``G_ji > 0``), ``x_i = upper_i`` (``G_ji < 0``); if it is ``>= h_j``
    that face is the set of least violation of row ``j`` (exactly its feasible set at equality).
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


def _dense_one(x_des, lower, upper, W, G, h, max_iter):
    infeasible = jnp.bool_(False)
    if G.shape[0]:
        lo, hi, G2, h2, infeasible = _pin_infeasible_rows(lower, upper, G, h)
    else:
        lo, hi, G2, h2 = lower, upper, G, h
    x, _, ok, it = _core(max_iter)(x_des, lo, hi, W, G2, h2)
    x = jnp.minimum(jnp.maximum(x, lower), upper)  # the box, exactly, whatever happened
    viol = jnp.max(jnp.maximum(G @ x - h, 0.0)) if G.shape[0] else jnp.zeros((), x.dtype)
    return x, ok > 0.5, it.astype(jnp.int32), infeasible, viol


def _flat_vmap(fn, batch_shape, *args):
    """Apply the single-problem ``fn`` over a flattened batch (all args already broadcast)."""
    size = int(np.prod(batch_shape)) if batch_shape else 1
    flat = [a.reshape((size,) + a.shape[len(batch_shape):]) for a in args]
    out = jax.vmap(fn)(*flat)
    return jax.tree.map(lambda o: o.reshape(batch_shape + o.shape[1:]), out)


@jax.jit(static_argnums=(6,))
def _dense_batched(x_des, lower, upper, W, G, h, max_iter):
    """All problems of a batch (inputs broadcast to ``batch + core`` shapes), one compiled program."""
    batch = x_des.shape[:-1]

    def one(xd, lo, hi, w, g, hh):
        return _dense_one(xd, lo, hi, w, g, hh, max_iter)

    return BoxQPResult(*_flat_vmap(one, batch, x_des, lower, upper, W, G, h))


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
        A row that no point of the box satisfies (``min_box G_j x > h_j``) is met with the least
        violation: ``x`` is held on the face of the box that minimises ``G_j x`` (the violation
        ``G_j x - h_j`` is then the smallest possible, and among those points the metric decides);
        ``infeasible`` is set. Rows that are each satisfiable but not jointly (only possible for
        ``m >= 2``) are not resolved exactly: ``converged`` is False there (documented limit).
      gradient: ``"exact"`` — implicit derivative of the solution (true derivative; at a tie the
        coordinate is free, the derivative from inside the box). ``"straight_through"`` — the value
        is the same projection but the derivative w.r.t. ``x_des`` is the identity and w.r.t. the
        other inputs zero (a learning heuristic, not the derivative of the projection).
      max_iter: active-set iterations per solve (default ``4 n + 4 m + 10``), static.

    Returns:
      ``BoxQPResult(x, converged, iterations, infeasible, violation)``. ``x`` satisfies the box
      exactly, always; it is never NaN for finite inputs.

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

        res = _dense_batched(x_des, lower, upper, W, G, h, int(max_iter))
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
