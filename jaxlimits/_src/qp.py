"""The differentiable box-QP projection (with optional halfspaces); see ``docs/qp.md``.

Solves, per problem of a batch,

    min_x  1/2 (x - x_des)^T W (x - x_des)   s.t.   lower <= x <= upper,   G x <= h.

* ``metric=None`` or a 1-D positive diagonal, no halfspaces: the exact clip, with a custom JVP
  (identity on free coordinates, zero on active ones; the tie rule is in ``_clip``).
* dense SPD metric and/or halfspaces (``_dense_batched``), three stages, the first two not
  differentiated; arrays have the batch as their first axis here (``(B, n)``, ``(B, n, n)``):
  1. the fast path (``qp_pdas.solve``): block principal pivoting from the split of a few
     Gauss-Seidel sweeps, every iteration an exact solve of the current active set, the batch
     ``qp_pdas.BLOCK`` problems at a time, late iterations on the unsettled problems alone;
  2. the robust path for the problems still unsettled after ``min(max_iter, n + 8)`` (``_fallback``, gathered
     ``chunk`` at a time): ``qp_active_set.solve``; for ``m >= 2`` the least violation of the rows
     first (``qp_bvls``), then the primal active-set method from a feasible point, on the set of
     least violation;
  3. the implicit derivative attached to the solution (``_attach``, a ``jax.custom_jvp``): the KKT
     system of the final active set of the problem actually solved (forward and reverse mode),
     block by block.
* The returned ``x`` is always clipped to the box at the end: the box holds exactly whatever the
  iteration count did.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from jaxlimits._src import qp_active_set, qp_bvls, qp_pdas
from jaxlimits._src.qp_checks import check_inputs
from jaxlimits._src.qp_linalg import kkt_solve, matvec, matvec_t

GRADIENTS = ("exact", "straight_through")
FAST_ITER_EXTRA = 8  # the fast path stops after n + 8 iterations (at most max_iter); see _dense_batched


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
# dense metric and halfspaces: the batch is the first axis of every array here


def _chunk(B: int) -> int:
    """Problems handed to the robust path at a time."""
    return min(B, max(16, B // 64))


class _Pending(NamedTuple):
    """The robust path's loop over chunks: ``out`` (``qp_active_set.Result``, batch first) and
    ``pending`` ``(B,)`` bool, the problems not yet handed to it."""

    out: qp_active_set.Result
    pending: jax.Array


def _fallback(args, fast: qp_active_set.Result, max_iter, chunk: int) -> qp_active_set.Result:
    """``qp_active_set.solve`` on the problems not ``fast.ok``, ``chunk`` at a time (gathered in and out).

    ``args``: ``(x_des, lower, upper, W, G, h)`` batch first. The others keep ``fast`` (their
    ``split`` is all False); ``it`` adds the fast path's iterations.
    """

    @jax.named_scope("robust_path")  # named in the compiled program (tests/test_qp.py checks where it runs)
    def body(c: _Pending) -> _Pending:
        idx = qp_pdas.pick(c.pending, chunk)
        sub = qp_pdas.take(tuple(args) + (c.out.x,), idx, 0)
        res = jax.vmap(lambda *a: qp_active_set.solve(*a, max_iter))(*sub)
        res = res._replace(it=res.it + qp_pdas.take(c.out.it, idx, 0))
        return _Pending(qp_pdas.put_back(c.out, res, idx, 0), c.pending.at[idx].set(False, mode="drop"))

    def robust(fast):
        return jax.lax.while_loop(lambda c: jnp.any(c.pending), body, _Pending(fast, ~fast.ok)).out

    # behind a cond although the loop would then run no iteration: for a batch of one, the gather of the one
    # pending problem has a constant index, so XLA hoisted the whole robust path out of the loop and ran it on
    # every call (one shielded Gymnasium decision's QP: 320 us instead of 110 us where the fast path settled)
    return jax.lax.cond(jnp.any(~fast.ok), robust, lambda fast: fast, fast)


# --------------------------------------------------------------------------------------------
# the derivative: implicit, attached to the solution of the problem actually solved


def _tangent(x, lam, free, primals, tangents, eq):
    """Implicit derivative: the KKT conditions of each problem's final active set (batch last; ``_attach_jvp``
    calls it for one problem, batch ``()``, and ``vmap``-s it).

    ``free`` ``(n, *batch)``: the coordinates free in the derivative (``active_free``); rows with
    ``lam > 0`` or in ``eq`` are held; ``W`` symmetric. ``tangents``: ``None`` for a zero tangent
    (its terms are left out). The active set's KKT system is factored anew (carrying the fast
    path's last factor out through its blocks and gathers measured no faster).
    """
    x_des, lower, upper, W, G, h = primals
    dxd, dl, du, dW, dG, dh = tangents
    dxa = None
    if dl is not None or du is not None:
        at_l = x <= 0.5 * (lower + upper)
        dxa = jnp.where(free, 0.0, jnp.where(at_l, 0.0 if dl is None else dl, 0.0 if du is None else du))
    r = jnp.zeros_like(x)
    s = jnp.zeros_like(lam)
    if dxd is not None:
        r = r + matvec(W, dxd)
    if dW is not None:
        r = r - matvec(dW, x - x_des)
    if dG is not None:
        r = r - matvec_t(dG, lam)
        s = s - matvec(dG, x)
    if dxa is not None:
        r = r - matvec(W, dxa)
        s = s - matvec(G, dxa)
    if dh is not None:
        s = s + dh
    dxf, _ = kkt_solve(W, G, free, (lam > 0) | eq, r, s)
    return dxf if dxa is None else dxf + dxa


@jax.custom_jvp
def _attach(x, lam, free, x_des, lower, upper, W, G, h, eq):
    """``x`` (the solution, computed without derivatives), with the implicit derivative attached.

    Batch first: ``x`` ``(B, n)``, ``lam`` ``(B, m)``, ``free`` ``(B, n)`` (``active_free``), the
    problem actually solved (``W`` as given: its symmetric part is the metric), ``eq`` ``(B, m)``.
    """
    return x


def _attach_jvp(primals, tangents):
    """The tangent of ``_attach``: one problem's (``_tangent`` at batch ``()``) ``vmap``-ed over the batch, so
    the derivative's program has the batch first; zero tangents (``symbolic_zeros``) are left out. Written
    batch last (``qp_linalg``'s layout, as the fast path) it cost 2-3x more in the backward pass (the
    transpose): ``benchmarks/bench_qp.py`` dense forward+backward at 4096, 2.48 -> 1.82 ms, forward 1.28 ms
    (docs/qp.md). Not block by block like the fast path: JAX 0.9 fails to transpose a ``lax.map`` inside a
    custom JVP, and ``linear_call`` (a linear map with its transpose given) has no batching rule, so ``vmap``
    of the derivative would break."""
    x, lam, free, x_des, lower, upper, W, G, h, eq = primals
    tangents = tuple(None if isinstance(t, SymbolicZero) else t for t in tangents[3:9])
    if all(t is None for t in tangents):
        return x, jnp.zeros_like(x)

    def sym(W):
        return None if W is None else 0.5 * (W + W.T)

    def one(x, lam, free, x_des, lower, upper, W, G, h, eq, tangents):
        dxd, dl, du, dW, dG, dh = tangents
        return _tangent(x, lam, free, (x_des, lower, upper, sym(W), G, h), (dxd, dl, du, sym(dW), dG, dh), eq)

    return x, jax.vmap(one)(x, lam, free, x_des, lower, upper, W, G, h, eq, tangents)


_attach.defjvp(_attach_jvp, symbolic_zeros=True)


@jax.custom_batching.custom_vmap
def _solve(x_des, lower, upper, W, G, h, max_iter) -> qp_active_set.Result:
    """The solution, without derivatives: the fast path, then the robust path for what it left unsettled.

    Batch first in and out (``(B, n)``, ``(B, n, n)``, ...). Under ``jax.vmap`` (a policy's per-env code, the
    shield inside a Brax env) the mapped axis joins the batch (``_solve_vmap``): one call on the whole batch,
    so the blocks, the cascade and the robust path's gathers work on it (a plain ``vmap`` would run every
    problem of the batch through as many iterations as its slowest one needs, in both paths). The inputs
    carry no tangents (``stop_gradient``): the derivative is attached outside (``_attach``).
    """
    n, m = x_des.shape[-1], G.shape[-2]
    B = x_des.shape[0]
    # the fast path gets at most FAST_ITER_EXTRA + n iterations: on the shield's torque-space problems (n = 7,
    # m = 14) it settles 99 % of the problems it ever settles within 12 and cycles on the rest (29 % of
    # Pusher-v5's, measured with 400 iterations); those go to the robust path instead of spending max_iter
    fast = qp_pdas.solve(x_des, lower, upper, W, G, h, jnp.minimum(max_iter, n + FAST_ITER_EXTRA))
    nz = n + m if m >= 2 else 0
    no = jnp.zeros((B,), bool)
    split0 = qp_active_set.Split(
        no,
        jnp.zeros((B, nz), bool),
        jnp.zeros((B, nz), bool),
        jnp.zeros((B, n), bool),
        jnp.zeros((B, n), bool),
        jnp.zeros((B, m), bool),
        jnp.zeros((B, m), bool),
    )
    args = (x_des, lower, upper, W, G, h)
    fast = qp_active_set.Result(fast.x, fast.lam, fast.settled, fast.iters, fast.free, split0)
    return _fallback(args, fast, max_iter, _chunk(B))


@_solve.def_vmap
def _solve_vmap(axis_size, in_batched, *args):
    """``_solve`` under ``vmap``: the mapped axis (first) joins the batch; inputs not mapped are broadcast.

    ``max_iter`` is one traced scalar per call (``solve_box_qp`` makes it a constant), never mapped.
    """
    *arrays, max_iter = args
    if in_batched[-1]:
        raise ValueError("max_iter of the box QP is one value per call; it cannot be mapped over")
    arrays = [a if b else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, b in zip(arrays, in_batched)]
    B = arrays[0].shape[1]
    out = _solve(*(a.reshape((axis_size * B,) + a.shape[2:]) for a in arrays), max_iter)
    out = jax.tree.map(lambda o: o.reshape((axis_size, B) + o.shape[1:]), out)
    return out, jax.tree.map(lambda _: True, out)


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
        lo, hi, Gp, hp, infeasible = jax.vmap(qp_active_set.pin_infeasible_rows)(lower, upper, G, h)

    sg = [jax.lax.stop_gradient(a) for a in (x_des, lo, hi, W, Gp, hp)]
    res = _solve(*sg, max_iter)
    x, lam = jax.lax.stop_gradient(res.x), jax.lax.stop_gradient(res.lam)

    eq = res.split.eq
    if m >= 2:  # the problem actually solved where some rows cannot hold together (differentiable)
        sp = res.split
        r = jax.lax.cond(
            jnp.any(sp.relax),
            lambda a: jax.vmap(qp_bvls.residual)(*a)[0],
            lambda a: jnp.zeros_like(a[3]),
            (lower, upper, G, h, sp.zfree, sp.zup),
        )
        infeasible = sp.relax
        lo = jnp.where(sp.pin_u, upper, lower)
        hi = jnp.where(sp.pin_l, lower, upper)
        Gp = jnp.where(sp.drop[..., None], 0.0, G)
        hp = jnp.where(sp.drop, 0.0, h + jnp.where(sp.relax[:, None], r, 0.0))
    x = _attach(x, lam, res.free, x_des, lo, hi, W, Gp, hp, eq)
    x = jnp.minimum(jnp.maximum(x, lower), upper)  # the box, exactly, whatever happened
    viol = jnp.max(jnp.maximum(jnp.einsum("bmn,bn->bm", G, x) - h, 0.0), axis=-1) if m else jnp.zeros((B,), x.dtype)
    res = BoxQPResult(x, res.ok, res.it.astype(jnp.int32), infeasible, viol)
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
      max_iter: iterations per solve of the robust path (default ``4 n + 4 m + 10``); the fast path
        stops after ``min(max_iter, n + 8)`` and hands what it has not settled to the robust path; not
        static (no recompilation).

    Returns:
      ``BoxQPResult(x, converged, iterations, infeasible, violation)``. ``x`` satisfies the box
      exactly, always; it is never NaN for finite inputs. A non-finite ``x_des`` (a NaN/inf command) is
      not refused (it may be traced): without rows or a dense metric ``x`` is its clip (NaN stays NaN),
      with them ``x`` may be NaN; ``converged`` is False for it either way (the shields replace non-finite
      commands by the braking action before projecting). ``iterations``: fast-path iterations
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
        res = BoxQPResult(
            x, jnp.ones(batch, bool), jnp.zeros(batch, jnp.int32), jnp.zeros(batch, bool), jnp.zeros(batch, dtype)
        )
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
    # x_des is the one input not checked eagerly (it is the policy's, traced): a non-finite command has no
    # projection to converge to
    finite = jnp.all(jnp.isfinite(x_des), axis=-1) & jnp.all(jnp.isfinite(res.x), axis=-1)
    res = res._replace(converged=res.converged & finite)
    if gradient == "straight_through":
        # value exactly res.x (x_des - x_des == 0), derivative the identity w.r.t. x_des
        res = res._replace(x=jax.lax.stop_gradient(res.x) + (x_des - jax.lax.stop_gradient(x_des)))
    return res


def project_box(
    x_des, lower, upper, metric=None, *, G=None, h=None, gradient: str = "exact", max_iter: int | None = None
) -> jax.Array:
    """``solve_box_qp(...).x``: the projection alone (see ``solve_box_qp`` for every argument).

    Shape ``(..., n)``, the dtype of the inputs; ``lower <= x <= upper`` exactly.
    """
    return solve_box_qp(x_des, lower, upper, metric, G=G, h=h, gradient=gradient, max_iter=max_iter).x
