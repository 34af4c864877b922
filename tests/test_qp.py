"""The box-QP projection against an exact enumeration reference, its derivatives, batching and errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.optimize import Bounds, minimize

import jaxlimits as jl
import qp_reference as ref
from jaxlimits._src import qp_active_set


def _spd(rng, batch, n, cond):
    """Random SPD matrices with condition number ``cond`` (random eigenbasis, log-spaced spectrum)."""
    Q, _ = np.linalg.qr(rng.normal(size=(batch, n, n)))
    eig = np.exp(rng.uniform(0, np.log(cond), size=(batch, n)))
    eig[:, 0], eig[:, -1] = 1.0, cond
    W = np.einsum("bij,bj,bkj->bik", Q, eig, Q)
    return 0.5 * (W + np.swapaxes(W, -1, -2)) * np.exp(rng.uniform(-3, 3, size=(batch, 1, 1)))


def _problems(rng, batch, n, cond, kind="random"):
    lo = rng.uniform(-2.0, 0.0, size=(batch, n))
    hi = lo + rng.uniform(0.1, 2.0, size=(batch, n))
    W = _spd(rng, batch, n, cond)
    xd = rng.uniform(-4.0, 4.0, size=(batch, n))
    if kind == "none_active":  # x_des inside: the answer is x_des
        xd = lo + rng.uniform(0.05, 0.95, size=(batch, n)) * (hi - lo)
    elif kind == "all_active":  # far outside along a diagonal metric's axes: every bound holds
        W = np.einsum("bi,ij->bij", rng.uniform(0.5, 2.0, size=(batch, n)), np.eye(n))
        xd = np.where(rng.uniform(size=(batch, n)) < 0.5, lo - 3.0, hi + 3.0)
    elif kind == "ties":  # x_des exactly on bounds, degenerate boxes lower == upper
        on = rng.integers(0, 3, size=(batch, n))
        xd = np.where(on == 1, lo, np.where(on == 2, hi, xd))
        flat = rng.uniform(size=(batch, n)) < 0.15
        hi = np.where(flat, lo, hi)
    return xd, lo, hi, W


def _max_error(res, xd, lo, hi, W, G=None, h=None):
    """Largest error relative to ``1 + |x_ref|`` over the batch (problems the reference cannot solve,
    degenerate ones where no active-set system is regular, are skipped; at most 1 % of them)."""
    errs, skipped = [], 0
    for i in range(len(xd)):
        gi = None if G is None else G[i]
        hi_ = None if G is None else ref.least_violation_h(lo[i], hi[i], G[i], h[i])
        try:
            xr = ref.solve(xd[i], lo[i], hi[i], W[i], gi, hi_)
        except RuntimeError:
            skipped += 1
            continue
        errs.append(np.max(np.abs(np.asarray(res.x[i], np.float64) - xr)) / (1.0 + np.max(np.abs(xr))))
    assert skipped <= 0.01 * len(xd), skipped
    return max(errs)


def _assert_in_box(x, lo, hi):
    x = np.asarray(x)
    assert np.all(np.isfinite(x))
    assert np.all(x >= np.asarray(lo, x.dtype)) and np.all(x <= np.asarray(hi, x.dtype))


# ---------------------------------------------------------------------------------------------- clip


def test_clip_is_exact_for_none_and_diagonal_metric(dtype):
    rng = np.random.default_rng(0)
    xd = rng.normal(size=(4096, 7)).astype(dtype) * 3
    lo, hi = -np.ones(7, dtype), np.linspace(0.0, 2.0, 7).astype(dtype)
    for metric in (None, np.linspace(0.1, 10.0, 7).astype(dtype)):
        res = jl.solve_box_qp(xd, lo, hi, metric)
        assert res.x.dtype == dtype
        np.testing.assert_array_equal(res.x, np.clip(xd, lo, hi))
        assert bool(jnp.all(res.converged)) and int(jnp.max(res.iterations)) == 0


def test_clip_derivative_is_true_and_decided_at_ties(dtype):
    lo = jnp.asarray([0.0, 0.0, 0.0, 0.0, 0.0, 1.0], dtype)
    hi = jnp.asarray([1.0, 1.0, 1.0, 1.0, 1.0, 1.0], dtype)
    xd = jnp.asarray([0.5, -1.0, 2.0, 0.0, 1.0, 1.0], dtype)  # free, below, above, tie lo, tie hi, flat box
    one = jnp.ones_like(xd)
    _, d_xd = jax.jvp(lambda x: jl.project_box(x, lo, hi), (xd,), (one,))
    _, d_lo = jax.jvp(lambda a: jl.project_box(xd, a, hi), (lo,), (one,))
    _, d_hi = jax.jvp(lambda b: jl.project_box(xd, lo, b), (hi,), (one,))
    np.testing.assert_array_equal(d_xd, [1, 0, 0, 1, 1, 0])  # a tie is free (derivative from inside)
    np.testing.assert_array_equal(d_lo, [0, 1, 0, 0, 0, 1])
    np.testing.assert_array_equal(d_hi, [0, 0, 1, 0, 0, 0])
    g = jax.grad(lambda x: jnp.sum(jl.project_box(x, lo, hi) ** 2))(xd)
    assert np.all(np.isfinite(g))


def test_straight_through_keeps_the_value_and_passes_the_gradient(dtype):
    rng = np.random.default_rng(1)
    xd = jnp.asarray(rng.normal(size=(8, 5)) * 3, dtype)
    W = jnp.asarray(_spd(rng, 1, 5, 10.0)[0], dtype)
    for metric in (None, W):
        exact = jl.project_box(xd, -1.0, 1.0, metric)
        st = jl.project_box(xd, -1.0, 1.0, metric, gradient="straight_through")
        np.testing.assert_array_equal(exact, st)
        _assert_in_box(st, -1.0, 1.0)
    g = jax.grad(lambda x: jnp.sum(jl.project_box(x, -1.0, 1.0, gradient="straight_through")))(xd)
    np.testing.assert_array_equal(g, np.ones_like(xd))


# ----------------------------------------------------------------------------------- dense metric


@pytest.mark.parametrize("n, per_kind", [(3, 150), (7, 25)])
def test_dense_metric_matches_reference_float64(x64, n, per_kind):
    """4 kinds x 3 condition numbers (1e2, 1e4, 1e6) in one batch: 1800 problems (n=3), 300 (n=7)."""
    rng = np.random.default_rng(n)
    parts = [
        _problems(rng, per_kind, n, cond, kind)
        for kind in ("random", "none_active", "all_active", "ties")
        for cond in (1e2, 1e4, 1e6)
    ]
    xd, lo, hi, W = (np.concatenate(p) for p in zip(*parts))
    res = jl.solve_box_qp(xd, lo, hi, W)
    assert bool(jnp.all(res.converged))
    _assert_in_box(res.x, lo, hi)
    assert _max_error(res, xd, lo, hi, W) <= 1e-8


def test_dense_metric_matches_reference_float32():
    rng = np.random.default_rng(11)
    parts = [_problems(rng, 100, 7, 100.0, kind) for kind in ("random", "none_active", "all_active", "ties")]
    args = [np.concatenate(p).astype(np.float32) for p in zip(*parts)]
    res = jl.solve_box_qp(*args)
    assert res.x.dtype == np.float32
    assert float(jnp.mean(res.converged)) >= 0.99
    _assert_in_box(res.x, args[1], args[2])
    assert _max_error(res, *[a.astype(np.float64) for a in args]) <= 1e-4


def test_box_holds_exactly_even_when_stopped_early(dtype):
    rng = np.random.default_rng(3)  # batch sizes of the reference tests: max_iter is traced, no recompilation
    xd, lo, hi, W = (a.astype(dtype) for a in _problems(rng, 400 if dtype == np.float32 else 300, 7, 1e4))
    res = jl.solve_box_qp(xd, lo, hi, W, max_iter=1)
    _assert_in_box(res.x, lo, hi)
    assert not bool(jnp.all(res.converged))


# ------------------------------------------------------------------------------------- halfspaces


def test_dense_metric_large_n_satisfies_kkt(x64):
    """n above the unrolled size (array form, LAPACK): the KKT conditions, checked in NumPy."""
    rng = np.random.default_rng(14)
    xd, lo, hi, W = _problems(rng, 64, 14, 1e3)
    res = jl.solve_box_qp(xd, lo, hi, W)
    assert bool(jnp.all(res.converged))
    _assert_in_box(res.x, lo, hi)
    x = np.asarray(res.x)
    g = np.einsum("bij,bj->bi", W, x - xd)
    tol = 1e-9 * np.max(np.abs(W), axis=(1, 2))[:, None] * (1.0 + np.max(np.abs(xd), axis=1))[:, None]
    at_lo, at_hi = x <= lo, x >= hi
    assert np.all(np.where(at_lo, g >= -tol, np.where(at_hi, g <= tol, np.abs(g) <= tol)))
    assert np.all(np.isfinite(np.asarray(jax.grad(lambda a: jnp.sum(jl.project_box(a, lo, hi, W) ** 2))(xd))))


def _contradicting_rows(rng, batch, n, m):
    """Rows each satisfiable in the box (some barely) but, with the second against the first, mostly not together."""
    xd, lo, hi, W = _problems(rng, batch, n, 1e2)
    G = rng.normal(size=(batch, m, n))
    G[:, 1] = -G[:, 0] * rng.uniform(0.5, 2.0, size=(batch, 1)) + 0.3 * rng.normal(size=(batch, n))
    gmin = np.sum(np.minimum(G * lo[:, None], G * hi[:, None]), axis=-1)
    spread = np.sum(np.abs(G) * (hi - lo)[:, None], axis=-1)
    h = gmin + rng.uniform(0.0, 0.3, size=(batch, m)) * spread
    h[: batch // 8, -1] = gmin[: batch // 8, -1] - 0.1  # and some rows the box alone rules out
    return xd, lo, hi, W, G, h


@pytest.mark.parametrize("n, m, batch", [(5, 1, 600), (4, 2, 400), (7, 1, 80), (4, 3, 120)])
def test_halfspaces_match_reference_float64(x64, n, m, batch):
    """Feasible rows vs the enumeration; rows that cannot all hold (m >= 2: random rows, and
    contradicting pairs) vs SciPy: least Euclidean violation over the box, then the metric."""
    rng = np.random.default_rng(10 * n + m)
    xd, lo, hi, W = _problems(rng, batch, n, 1e3)
    G = rng.normal(size=(batch, m, n))
    h = rng.normal(size=(batch, m)) + 0.5
    if m == 1:  # a quarter of the single rows cannot be met inside the box at all
        gmin = np.sum(np.minimum(G * lo[:, None], G * hi[:, None]), axis=-1)
        h = np.where(np.arange(batch)[:, None] % 4 == 0, gmin - rng.uniform(0.01, 1.0, size=(batch, m)), h)
    else:  # the second half: rows each (mostly) satisfiable, contradicting each other
        k = batch // 2
        xd[k:], lo[k:], hi[k:], W[k:], G[k:], h[k:] = _contradicting_rows(rng, batch - k, n, m)
    res = jl.solve_box_qp(xd, lo, hi, W, G=G, h=h)
    _assert_in_box(res.x, lo, hi)
    assert bool(jnp.all(res.converged))
    gmin = np.sum(np.minimum(G * lo[:, None], G * hi[:, None]), axis=-1)
    if m == 1:
        np.testing.assert_array_equal(res.infeasible, gmin[:, 0] > h[:, 0])
        # least violation: nothing in the box does better than the returned point
        np.testing.assert_allclose(res.violation, np.maximum(gmin[:, 0] - h[:, 0], 0.0), atol=1e-12)
        assert _max_error(res, xd, lo, hi, W, G, h) <= 1e-8
    else:  # rows may contradict each other (or one alone the box): an LP decides feasibility
        feasible = np.array([ref.rows_feasible(lo[i], hi[i], G[i], h[i]) for i in range(batch)])
        assert 0.1 < feasible.mean() < 0.9
        np.testing.assert_array_equal(res.infeasible, ~feasible)
        assert float(np.max(np.asarray(res.violation)[feasible])) <= 1e-12
        idx = np.flatnonzero(feasible)
        sub = jax.tree.map(lambda a: a[idx], res)
        assert _max_error(sub, xd[idx], lo[idx], hi[idx], W[idx], G[idx], h[idx]) <= 1e-8
        x = np.asarray(res.x)
        for i in np.flatnonzero(~feasible):
            xr, r = ref.solve_least_violation(xd[i], lo[i], hi[i], W[i], G[i], h[i])
            np.testing.assert_allclose(np.maximum(G[i] @ x[i] - h[i], 0.0), r, atol=1e-9)
            np.testing.assert_allclose(res.violation[i], np.max(r), atol=1e-9)
            assert np.max(np.abs(x[i] - xr)) <= 1e-6 * (1.0 + np.max(np.abs(xr))), i


def test_halfspaces_float32():
    rng = np.random.default_rng(5)
    xd, lo, hi, W = _problems(rng, 300, 5, 30.0)
    G = rng.normal(size=(300, 1, 5))
    h = rng.normal(size=(300, 1)) + 0.5
    args = [a.astype(np.float32) for a in (xd, lo, hi, W, G, h)]
    res = jl.solve_box_qp(*args[:4], G=args[4], h=args[5])
    _assert_in_box(res.x, args[1], args[2])
    assert float(jnp.mean(res.converged)) >= 0.98
    ok = np.flatnonzero(np.asarray(res.converged))
    sub = jax.tree.map(lambda a: a[ok], res)
    a64 = [a.astype(np.float64)[ok] for a in args]
    assert _max_error(sub, *a64) <= 1e-4


def test_contradicting_rows_float32_and_gradients():
    rng = np.random.default_rng(8)
    xd, lo, hi, W, G, h = (a.astype(np.float32) for a in _contradicting_rows(rng, 64, 5, 2))

    def loss(x, hh):  # one compiled program for the values and the gradients
        res = jl.solve_box_qp(x, lo, hi, W, G=G, h=hh)
        return jnp.sum(res.x**2), res

    (_, res), grads = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(xd, h)
    _assert_in_box(res.x, lo, hi)
    assert float(jnp.mean(res.converged)) >= 0.95
    feasible = np.array([ref.rows_feasible(lo[i], hi[i], G[i], h[i]) for i in range(len(xd))])
    assert np.mean(np.asarray(res.infeasible) == ~feasible) >= 0.95  # float32 may call a near-tie either way
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


# ------------------------------------------------------------------------------------- derivatives


def _nontie_problem(rng, n, m):
    """A problem whose active set is stable under small perturbations (no ties, margins > 0.05)."""
    while True:
        xd, lo, hi, W = (a[0] for a in _problems(rng, 1, n, 20.0))
        G = rng.normal(size=(m, n))
        h = rng.normal(size=(m,)) + 0.3
        with jax.enable_x64(True):
            res = jl.solve_box_qp(xd, lo, hi, W, G=G if m else None, h=h if m else None)
            x = np.asarray(res.x)
            g = W @ (x - xd)
        gaps = np.minimum(np.abs(x - lo), np.abs(x - hi))
        free = gaps > 0.05
        bound = gaps == 0.0
        if m:
            slack = h - G @ x
            if not (np.all((np.abs(slack) < 1e-9) | (slack > 0.05)) and np.any(np.abs(slack) < 1e-9)):
                continue
            # the row's multiplier must be clearly positive: dropping it must change the answer
            with jax.enable_x64(True):
                x0 = np.asarray(jl.project_box(xd, lo, hi, W))
            if np.max(np.abs(x0 - x)) < 0.05:
                continue
        if np.all(free | bound) and np.all(np.abs(g[bound]) > 0.05) and free.sum() >= 1 and bound.sum() >= 1:
            return xd, lo, hi, W, G, h


@pytest.mark.parametrize("m", [0, 1])
def test_implicit_gradients_match_finite_differences(x64, m):
    rng = np.random.default_rng(7 + m)
    for _ in range(3):
        xd, lo, hi, W, G, h = _nontie_problem(rng, 4, m)
        args = (xd, lo, hi, W) + ((G, h) if m else ())

        def f(x, a, b, w, *gh):  # the metric enters symmetrised: finite differences perturb it freely
            w = 0.5 * (w + w.T)
            return jl.project_box(x, a, b, w, G=gh[0], h=gh[1]) if gh else jl.project_box(x, a, b, w)

        check_grads(f, args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-5)


def test_implicit_gradients_through_the_least_violation(x64):
    """Contradicting rows: the derivative includes that of the least violation ``r*`` (the split fixed)."""
    rng = np.random.default_rng(3)
    xd, lo, hi, W, G, h = _contradicting_rows(rng, 16, 4, 2)
    checked = 0
    for i in range(16):
        args = (xd[i], lo[i], hi[i], W[i], G[i], h[i])
        res = jl.solve_box_qp(*args[:4], G=G[i], h=h[i])
        if not bool(res.infeasible) or checked == 3:
            continue

        def f(x, a, b, w, g, hh):
            return jl.project_box(x, a, b, 0.5 * (w + w.T), G=g, h=hh)

        check_grads(f, args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5, rtol=1e-5)
        checked += 1
    assert checked == 3


def test_implicit_jacobian_matches_the_closed_form_on_a_batch(x64):
    """A batch large enough for the fast path's cascade (n = 5, 600 problems, no rows): forward and
    reverse mode vs ``dx_F / dx_des = [I, W_FF^-1 W_FA]`` and ``dx_A / dx_des = 0`` of each problem's
    active set, on the problems whose active set is stable (margins > 1e-6)."""
    rng = np.random.default_rng(12)
    xd, lo, hi, W = _problems(rng, 600, 5, 1e2)
    x = np.asarray(jl.project_box(xd, lo, hi, W))
    u, t = rng.normal(size=xd.shape), rng.normal(size=xd.shape)
    jtu = np.asarray(jax.grad(lambda a: jnp.sum(jl.project_box(a, lo, hi, W) * u))(xd))
    jt = np.asarray(jax.jvp(lambda a: jl.project_box(a, lo, hi, W), (xd,), (t,))[1])
    checked = 0
    for i in range(len(xd)):
        g = W[i] @ (x[i] - xd[i])
        held = (x[i] == lo[i]) | (x[i] == hi[i])
        margin = np.minimum(x[i] - lo[i], hi[i] - x[i])
        if np.any(held & (np.abs(g) < 1e-6)) or np.any(~held & (margin < 1e-6)):
            continue
        F, A = np.flatnonzero(~held), np.flatnonzero(held)
        J = np.zeros((5, 5))
        J[F, F] = 1.0
        J[np.ix_(F, A)] = np.linalg.solve(W[i][np.ix_(F, F)], W[i][np.ix_(F, A)]) if len(F) else 0.0
        np.testing.assert_allclose(jt[i], J @ t[i], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(jtu[i], J.T @ u[i], rtol=1e-9, atol=1e-9)
        checked += 1
    assert checked >= 0.9 * len(xd)


def test_gradients_are_finite_at_ties_and_degenerate_problems(dtype):
    rng = np.random.default_rng(9)
    xd, lo, hi, W = (a.astype(dtype) for a in _problems(rng, 64, 3, 1e3, "ties"))
    G = rng.normal(size=(64, 1, 3)).astype(dtype)
    gmin = np.sum(np.minimum(G * lo[:, None], G * hi[:, None]), axis=-1)
    h = (gmin + np.where(np.arange(64)[:, None] % 2 == 0, 0.0, -0.5)).astype(dtype)  # tight / infeasible

    def loss(x, a, b, w, g, hh):
        return jnp.sum(jl.project_box(x, a, b, w) ** 2) + jnp.sum(jl.project_box(x, a, b, w, G=g, h=hh) ** 2)

    grads = jax.grad(loss, argnums=tuple(range(6)))(xd, lo, hi, W, G, h)
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


# ----------------------------------------------------------------------------- batching, jit, vmap


def test_jit_eager_vmap_agree_and_broadcast(dtype):
    rng = np.random.default_rng(4)
    xd = rng.normal(size=(3, 4, 3)).astype(dtype) * 3
    W = _spd(rng, 1, 3, 100.0)[0].astype(dtype)
    G = rng.normal(size=(2, 3)).astype(dtype)
    h = np.asarray([0.5, 0.3], dtype)
    lo, hi = np.asarray(-1.0, dtype), np.full((3,), 1.0, dtype)
    for kw in ({"G": G, "h": h},):
        eager = jl.project_box(xd, lo, hi, W, **kw)
        assert eager.shape == (3, 4, 3) and eager.dtype == dtype
        jitted = jax.jit(lambda x: jl.project_box(x, lo, hi, W, **kw))(xd)
        mapped = jax.vmap(jax.vmap(lambda x: jl.project_box(x, lo, hi, W, **kw)))(xd)
        np.testing.assert_allclose(eager, jitted, rtol=0, atol=1e3 * np.finfo(dtype).eps)
        np.testing.assert_allclose(eager, mapped, rtol=0, atol=1e3 * np.finfo(dtype).eps)
    res = jl.solve_box_qp(xd, lo, hi, np.broadcast_to(W, (4, 3, 3)))
    assert res.converged.shape == (3, 4) and res.iterations.dtype == jnp.int32


def test_batches_larger_than_a_block_match_reference_and_the_unblocked_answer(x64):
    """More than ``qp_pdas.BLOCK`` problems run block by block (the last block filled with copies):
    every answer matches the enumeration and the answer of the same problems solved in a small batch."""
    from jaxlimits._src.qp_pdas import BLOCK

    rng = np.random.default_rng(13)
    B = 2 * BLOCK + 5
    xd, lo, hi, W = _problems(rng, B, 3, 1e3)
    res = jl.solve_box_qp(xd, lo, hi, W)
    assert bool(jnp.all(res.converged))
    _assert_in_box(res.x, lo, hi)
    assert _max_error(res, xd, lo, hi, W) <= 1e-8
    tail = slice(B - 40, B)  # the last, padded block
    small = jl.project_box(xd[tail], lo[tail], hi[tail], W[tail])
    np.testing.assert_allclose(res.x[tail], small, rtol=0, atol=1e-12)
    g = jax.grad(lambda a: jnp.sum(jl.project_box(a, lo, hi, W) ** 2))(xd)
    g_small = jax.grad(lambda a: jnp.sum(jl.project_box(a, lo[tail], hi[tail], W[tail]) ** 2))(xd[tail])
    np.testing.assert_allclose(g[tail], g_small, rtol=0, atol=1e-10)


def test_vmap_of_the_derivatives_matches_a_loop(x64):
    """``vmap`` of ``grad`` and of ``jvp`` (the implicit derivative under an outer batch)."""
    rng = np.random.default_rng(15)
    A = rng.normal(size=(3, 5, 4, 4))
    W = A @ np.swapaxes(A, -1, -2) + np.eye(4)
    xd, G, h = 2.0 * rng.normal(size=(3, 5, 4)), rng.normal(size=(3, 5, 1, 4)), rng.uniform(size=(3, 5, 1))

    def f(x, w, g, hh):
        return jnp.sum(jl.project_box(x, -1.0, 1.0, w, G=g, h=hh) ** 2)

    grads = jax.vmap(jax.grad(f, argnums=(0, 1, 2, 3)))(xd, W, G, h)
    tangents = jax.vmap(lambda x, t, w: jax.jvp(lambda y: jl.project_box(y, -1.0, 1.0, w), (x,), (t,))[1])(xd, xd, W)
    for i in range(3):
        for got, want in zip(grads, jax.grad(f, argnums=(0, 1, 2, 3))(xd[i], W[i], G[i], h[i])):
            np.testing.assert_allclose(got[i], want, rtol=1e-12, atol=1e-12)
        want = jax.jvp(lambda y: jl.project_box(y, -1.0, 1.0, W[i]), (xd[i],), (xd[i],))[1]
        np.testing.assert_allclose(tangents[i], want, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------ errors


@pytest.mark.parametrize(
    "args, kwargs, match",
    [
        ((np.zeros(3), 1.0, -1.0), {}, r"lower <= upper.*lower=\[1\.0"),
        ((np.zeros(3), np.zeros(2), 1.0), {}, r"lower must be a scalar or end in n=3"),
        ((np.zeros(3), -np.inf, 1.0), {}, r"lower must be finite"),
        ((np.zeros(3), -1.0, 1.0, np.diag([1.0, -1.0, 1.0])), {}, r"symmetric positive definite.*-1\.0"),
        ((np.zeros(3), -1.0, 1.0, np.array([[1.0, 2, 0], [0, 1, 0], [0, 0, 1]])), {}, r"metric must be symmetric"),
        ((np.zeros(3), -1.0, 1.0, np.array([1.0, 0.0, 1.0])), {}, r"diagonal metric must be > 0"),
        ((np.zeros(3), -1.0, 1.0, np.eye(2)), {}, r"dense metric must have shape"),
        ((np.zeros(3), -1.0, 1.0), {"G": np.ones((1, 3))}, r"G and h go together"),
        (
            (np.zeros(3), -1.0, 1.0),
            {"G": np.ones((2, 3)), "h": np.ones(3)},
            r"h must have shape \(\.\.\., m\) with m=2",
        ),
        ((np.zeros(3), -1.0, 1.0), {"G": np.ones((2, 4)), "h": np.ones(2)}, r"G must have shape"),
        ((np.zeros(3), -1.0, 1.0), {"G": np.full((1, 3), np.nan), "h": np.ones(1)}, r"G must be finite"),
        ((np.zeros(3), -1.0, 1.0), {"gradient": "smooth"}, r"gradient must be one of"),
        ((np.float32(0.0), -1.0, 1.0), {}, r"x_des must have shape"),
    ],
)
def test_bad_inputs_raise_eagerly(args, kwargs, match):
    with pytest.raises(ValueError, match=match):
        jl.project_box(*args, **kwargs)


# ------------------------------------------------------------- redundant, parallel and far-away rows

_FAR_G = [0.947, -0.203, 0.249, -0.947, 0.203, -0.249, 0.993, -0.993, 0.947, -0.203, 0.249, -0.947, 0.203, -0.249]
_FAR_H = [0.593, 0.659, 0.276, 0.407, 0.341, 0.724, 0.928, 0.872, 3995, 7686, 8899, 7833, 4413, 8576]


def test_far_redundant_rows_do_not_make_a_feasible_problem_infeasible(dtype):
    """Regression: x_des = 0 meets every row and the box, yet the far rows' rounding (h ~ 1e4) in
    the least-violation stage made it look infeasible and returned the corner x = 10 as converged."""
    G, h = jnp.asarray(_FAR_G, dtype)[:, None], jnp.asarray(_FAR_H, dtype)
    res = jl.solve_box_qp(jnp.zeros(1, dtype), -10.0, 10.0, G=G, h=h)
    assert float(res.x[0]) == 0.0
    assert bool(res.converged) and not bool(res.infeasible) and float(res.violation) == 0.0


# A shielded UR5e decision (``JointLimitShield``, viability, the campaign's ``toward_limit``), written in the
# acceleration: the bounds are the box, the servos' torque limits the rows ``tau_lo <= M a - f <= tau_hi``.
# The wrist_3 row is met only at its face (least violation 0.0037 N m, below what float32 can certify), and the
# float32 mass matrix gives it rounding-level coefficients (4.8e-10) on every other joint.
_UR5E = dict(
    a_in=[-149.9305877685547, 116.67615509033203, 26.280738830566406, 65.4450912475586, 96.29039001464844, -93.38136291503906],
    lower=[0.0004053115553688258, -5.497968673706055, -23.037704467773438, -21.37803077697754, -26.46516227722168, -27.265138626098633],
    upper=[8.344832420349121, -0.00016689299081917852, 23.037704467773438, -7.152556645451114e-05, 26.46516227722168, 27.265138626098633],
    tau_lo=[-135.0, -135.0, -143.962158203125, -25.19999885559082, -25.19999885559082, 8.182083129882812],
    tau_hi=[135.0, 135.0, -35.28095245361328, 25.19999885559082, 25.19999885559082, 26.956951141357422],
    f=[0.6953582763671875, -1.799835205078125, -2.9229202270507812, -0.6734123229980469, 0.09234619140625, -0.0002307891845703125],
    M=[1.1509253978729248, 0.24307073652744293, -0.16536766290664673, -0.01864434778690338, 0.004781678784638643, 5.758084171247901e-06,
       0.24307073652744293, 1.5824227333068848, -0.03596181422472, 0.016543203964829445, -0.001167112379334867, 0.00013139177463017404,
       -0.16536766290664673, -0.03596181422472, 1.543941617012024, 0.07052452117204666, -0.006695072632282972, 0.0001313933898927644,
       -0.01864434778690338, 0.016543203964829445, 0.07052452117204666, 0.3193431496620178, -0.0014495282666757703, 0.0001313919055974111,
       0.004781678784638643, -0.001167112379334867, -0.006695072632282972, -0.0014495282666757703, 0.30341818928718567, 4.797610642093275e-10,
       5.758084171247901e-06, 0.00013139177463017404, 0.0001313933898927644, 0.0001313919055974111, 4.797610642093275e-10, 0.300132155418396],
)  # fmt: skip


def test_a_row_met_only_at_its_face_pins_only_the_coordinates_that_move_it(dtype):
    """Regression: the least-violation stage pinned every coordinate with a nonzero coefficient in a row it
    found tight, rounding-level ones too (here all six at their upper bounds), and returned that corner
    (violating the elbow's row by 72 N m) as not converged, not infeasible; the shield then used it. Now it
    converges to the least-violation projection (float32: to its tolerance), every row held to ~ the least
    violation."""
    d = {k: np.asarray(v, np.float64) for k, v in _UR5E.items()}
    M = d["M"].reshape(6, 6)
    G = np.concatenate([M, -M])
    h = np.concatenate([d["tau_hi"] + d["f"], -(d["tau_lo"] + d["f"])])
    r_star, _ = ref.least_violation(d["lower"], d["upper"], G, h)
    assert 1e-3 < np.max(r_star) < 1e-2  # met only at its face: a tie float32 cannot resolve
    args = [jnp.asarray(a, dtype) for a in (d["a_in"], d["lower"], d["upper"], M, G, h)]
    # the robust path, where solve_box_qp hands this problem (the fast path does not settle it); jitted alone
    # it compiles in ~2 s, the whole solve at this shape in ~50 s per dtype
    res = jax.jit(qp_active_set.solve, static_argnums=7)(*args, jnp.clip(args[0], args[1], args[2]), 82)
    _assert_in_box(res.x, args[1], args[2])
    x = np.asarray(res.x, np.float64)
    assert bool(res.ok)
    # the reference: SciPy's SLSQP on the rows relaxed by r* (the enumeration takes ~40 s at m = 12)
    hr = h + r_star + 1e-11 * (1.0 + np.abs(h))
    xr = minimize(
        lambda y: 0.5 * (y - d["a_in"]) @ M @ (y - d["a_in"]),
        np.clip(d["a_in"], d["lower"], d["upper"]),
        jac=lambda y: M @ (y - d["a_in"]),
        bounds=Bounds(d["lower"], d["upper"]),
        constraints=[{"type": "ineq", "fun": lambda y: hr - G @ y, "jac": lambda y: -G}],
        method="SLSQP",
        options=dict(maxiter=500, ftol=1e-15),
    ).x
    assert np.max(G @ xr - hr) <= 1e-9
    if dtype == jnp.float64:
        assert np.max(np.abs(x - xr)) <= 1e-6 * (1.0 + np.max(np.abs(xr))) and bool(res.split.relax)
    else:
        # float32 cannot tell this face from a feasible row (its least violation is below the tolerance), and
        # the set of least violation is thin (1e-3 N m more on the row lets the answer move by ~6 rad/s^2): the
        # answer is right to its tolerance in the backward sense, every row held to it, no worse an objective
        obj = lambda y: 0.5 * (y - d["a_in"]) @ M @ (y - d["a_in"])  # noqa: E731
        assert np.max(G @ x - h) <= np.max(r_star) + 1e-4 * np.max(np.abs(h))
        assert obj(x) <= obj(xr) * (1.0 + 1e-6)


# Found by tests/test_fuzz_core.py (hypothesis, in one test order): a contradicting pair of rows at +-1e30 (the
# fuzzer's "far" rows), float32, with a box of width 0 (``flat``) or not. ||r*||^2 overflowed, so the certificate
# of infeasibility was inf > inf (False) and the problem looked feasible (converged False, rows violated by 2);
# and the fast path's solve overflowed to NaN, which passes every KKT test (NaN compares False): "settled".
_FAR_PAIR = dict(
    x_des=[-3.0733056, -1.1863201, -7.237663],
    lower=[-0.7260766, -1.4604266, -1.9180529],
    upper=[-0.69302136, 0.16611391, -0.0925418],
    G=[[1.3664634, -0.6651947, 0.35151008], [0.90347016, 0.0940123, -0.7434993],
       [-0.90347016, -0.0940123, 0.7434993], [-1.0096182, -0.20917557, -0.15922502]],
    h=[5.408456e-01, 1.0e30, -1.0e30, -6.538286e-01],
)  # fmt: skip


@pytest.mark.parametrize("flat", [False, True])
def test_rows_out_of_reach_by_1e30_are_certified_infeasible_in_float32(flat):
    d = {k: np.asarray(v, np.float32) for k, v in _FAR_PAIR.items()}
    upper = d["lower"] if flat else d["upper"]
    W = np.eye(3, dtype=np.float32) * (1.0 if flat else 1e3)
    res = jl.solve_box_qp(d["x_des"], d["lower"], upper, W, G=d["G"], h=d["h"])
    _assert_in_box(res.x, d["lower"], upper)
    assert bool(res.converged) and bool(res.infeasible)
    assert float(res.violation) == pytest.approx(1e30, rel=1e-6)
    # the reachable rows hold at the least violation (SciPy's, in float64)
    G64, h64 = d["G"].astype(np.float64), d["h"].astype(np.float64)
    lo64 = d["lower"].astype(np.float64)
    if flat:  # the box is one point (SciPy's BVLS needs lower < upper)
        r_star = np.maximum(G64 @ lo64 - h64, 0.0)
    else:
        r_star, _ = ref.least_violation(lo64, upper.astype(np.float64), G64, h64)
    near = np.abs(h64) < 1e6
    assert np.all(G64[near] @ np.asarray(res.x, np.float64) - h64[near] <= r_star[near] + 1e-4)


def _redundant_rows(rng, batch):
    """n = 7 problems whose effective size is 1..7 (the rest flat at 0, outside every row), each with
    3 rows and copies of them: an exact duplicate, a scaled parallel row, an opposite row (a slab,
    possibly empty), a far-away copy and far-away random rows (h ~ 1e3..1e4)."""
    n = 7
    xd, lo, hi, W = _problems(rng, batch, n, 1e2)
    G0 = rng.normal(size=(batch, 3, n))
    k = 1 + np.arange(batch) % n
    act = np.arange(n)[None, :] < k[:, None]
    lo, hi, xd = np.where(act, lo, 0.0), np.where(act, hi, 0.0), np.where(act, xd, 1.0)
    W = np.where(act[:, :, None] & act[:, None, :], W, 0.0) + np.where(~act, 1.0, 0.0)[:, :, None] * np.eye(n)
    G0 = np.where(act[:, None], G0, 0.0)
    gmin = np.sum(np.minimum(G0 * lo[:, None], G0 * hi[:, None]), -1)
    spread = np.sum(np.abs(G0) * (hi - lo)[:, None], -1)
    h0 = gmin + rng.uniform(-0.05, 0.6, size=(batch, 3)) * spread
    c = rng.uniform(0.3, 3.0, size=(batch, 1))
    far = rng.uniform(1e3, 1e4, size=(batch, 3))
    G = np.concatenate(
        [
            G0,
            G0[:, :1],
            c[:, :, None] * G0[:, 1:2],
            -G0[:, :1],
            G0[:, 2:3],
            np.where(act[:, None], rng.normal(size=(batch, 1, n)), 0.0),
            -G0[:, 1:2],
        ],
        1,
    )
    h = np.concatenate(
        [
            h0,
            h0[:, :1],
            c * (h0[:, 1:2] + rng.uniform(-0.1, 0.5, size=(batch, 1)) * spread[:, 1:2]),
            -h0[:, :1] + rng.uniform(-0.2, 1.0, size=(batch, 1)) * spread[:, :1],
            far,
        ],
        1,
    )
    return xd, lo, hi, W, G, h, k


def _essential_rows(lo, hi, G, h):
    """The same feasible set with fewer rows (for the enumeration): rows no box point reaches dropped,
    of rows with the same direction the tightest kept."""
    keep = np.sum(np.maximum(G * lo, G * hi), 1) > h - 1e-9 * (1 + np.abs(h))
    G, h = G[keep], h[keep]
    nrm = np.linalg.norm(G, axis=1)
    U, c = G / nrm[:, None], h / nrm
    out = []
    for j in np.argsort(c):
        if not any(np.max(np.abs(U[j] - U[k])) < 1e-12 for k in out):
            out.append(j)
    return G[out], h[out]


def test_redundant_parallel_and_far_rows_match_reference(x64):
    """Random duplicate / parallel / opposite / far-away rows, 1..7 variables, vs SciPy (feasibility:
    linprog; least violation: lsq_linear) and the enumeration (on the essential rows)."""
    rng = np.random.default_rng(21)
    batch = 96  # > the fast path's hand-off count: both paths run
    xd, lo, hi, W, G, h, k = _redundant_rows(rng, batch)
    res = jl.solve_box_qp(xd, lo, hi, W, G=G, h=h)
    _assert_in_box(res.x, lo, hi)
    x, conv = np.asarray(res.x), np.asarray(res.converged)
    assert conv.mean() >= 0.95
    feasible = np.array([ref.rows_feasible(lo[i], hi[i], G[i], h[i]) for i in range(batch)])
    assert 0.1 < feasible.mean() < 0.9
    np.testing.assert_array_equal(res.infeasible, ~feasible)
    assert float(np.max(np.asarray(res.violation)[feasible])) <= 1e-12
    for i in range(batch):
        s = slice(0, k[i])
        r = np.zeros(G.shape[1])
        if not feasible[i]:
            r, _ = ref.least_violation(lo[i, s], hi[i, s], G[i, :, s], h[i])
            np.testing.assert_allclose(np.maximum(G[i] @ x[i] - h[i], 0.0), r, atol=1e-9)
        slack = 0 if feasible[i] else 1e-11 * (1 + np.abs(h[i]))
        Ge, he = _essential_rows(lo[i, s], hi[i, s], G[i, :, s], h[i] + r + slack)
        xr = ref.solve(xd[i, s], lo[i, s], hi[i, s], W[i, s, s], Ge, he)
        err = np.max(np.abs(x[i, s] - xr)) / (1.0 + np.max(np.abs(xr)))
        assert not conv[i] or err <= (1e-8 if feasible[i] else 1e-6), (i, err)


def _duplicate_rows(rng, batch):
    """n = 7 problems of effective size 2..7 (the rest flat at 0) with 3 random rows through a point
    inside the box (feasible), x_des far outside (rows active at the solution), and exact copies of
    the rows: all three again in reverse order and the first once more (m = 7)."""
    n = 7
    xd, lo, hi, W = _problems(rng, batch, n, 1e2)
    k = 2 + np.arange(batch) % (n - 1)
    act = np.arange(n)[None, :] < k[:, None]
    lo, hi, xd = np.where(act, lo, 0.0), np.where(act, hi, 0.0), np.where(act, 3.0 * xd, 1.0)
    W = np.where(act[:, :, None] & act[:, None, :], W, 0.0) + np.where(~act, 1.0, 0.0)[:, :, None] * np.eye(n)
    G0 = np.where(act[:, None], rng.normal(size=(batch, 3, n)), 0.0)
    p = lo + rng.uniform(0.2, 0.8, size=(batch, n)) * (hi - lo)
    h0 = np.einsum("bjn,bn->bj", G0, p)
    G = np.concatenate([G0, G0[:, ::-1], G0[:, :1]], 1)
    h = np.concatenate([h0, h0[:, ::-1], h0[:, :1]], 1)
    return xd, lo, hi, W, G, h, k


def test_duplicate_active_rows_do_not_make_the_active_set_method_cycle(x64):
    """Regression: with exact duplicate rows active, rounding let a copy of a held row (or a bound
    the held rows already fix) join the working set at a zero step; the dependent working set gave a
    negative multiplier, the copy was released and re-added forever: converged = False and x off by
    up to ~0.4 on ~25 % of these problems. The working set now stays independent."""
    rng = np.random.default_rng(5)
    batch = 128  # > the fast path's hand-off count: most go through the robust path
    xd, lo, hi, W, G, h, k = _duplicate_rows(rng, batch)
    res = jl.solve_box_qp(xd, lo, hi, W, G=G, h=h)
    _assert_in_box(res.x, lo, hi)
    x, conv = np.asarray(res.x), np.asarray(res.converged)
    assert not np.any(np.asarray(res.infeasible))
    assert conv.mean() >= 0.99, conv.mean()
    for i in range(batch):
        s = slice(0, k[i])
        xr = ref.solve(xd[i, s], lo[i, s], hi[i, s], W[i, s, s], G[i, :3, s], h[i, :3])
        err = np.max(np.abs(x[i, s] - xr)) / (1.0 + np.max(np.abs(xr)))
        assert not conv[i] or err <= 1e-8, (i, err)


def test_vmap_joins_the_batch_and_equals_the_batched_solve(x64):
    """Under ``vmap`` the solver takes the mapped axis into its batch (``qp._solve_vmap``): every field equals
    the batched call's, with mapped and shared (broadcast) inputs, nested maps, contradicting rows (least
    violation, flagged); the enumeration reference checks the shared-metric answers."""
    rng = np.random.default_rng(31)
    B, n = 24, 4
    xd, lo, hi, W = _problems(rng, B, n, 1e3)
    G = rng.normal(size=(B, 2, n))
    h = rng.uniform(0.0, 1.0, size=(B, 2))
    bad = rng.uniform(size=B) < 0.3
    G[bad, 1], h[bad, 1] = -G[bad, 0], -h[bad, 0] - 1.0  # g x <= h and g x >= h + 1: no box point meets both

    def same(a, b):
        for name, x, y in zip(jl.BoxQPResult._fields, a, b):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-12, err_msg=name)

    full = jl.solve_box_qp(xd, lo, hi, W, G=G, h=h)
    assert np.any(bad) and np.all(np.asarray(full.infeasible)[bad])  # (other rows may miss the random box too)
    same(jax.vmap(lambda *a: jl.solve_box_qp(*a[:4], G=a[4], h=a[5]))(xd, lo, hi, W, G, h), full)
    same(jax.jit(jax.vmap(lambda *a: jl.solve_box_qp(*a[:4], G=a[4], h=a[5])))(xd, lo, hi, W, G, h), full)
    # shared box and metric (not mapped: broadcast inside the rule)
    shared = jl.solve_box_qp(xd, lo[0], hi[0], W[0])
    same(jax.vmap(lambda x: jl.solve_box_qp(x, lo[0], hi[0], W[0]))(xd), shared)
    lo0, hi0, W0 = (np.broadcast_to(a[0], a.shape) for a in (lo, hi, W))
    assert _max_error(shared, xd, lo0, hi0, W0) <= 1e-8
    # nested maps over a (4, 6) batch, and a map over a batched call
    r = lambda a: a.reshape((4, 6) + a.shape[1:])  # noqa: E731
    nested = jax.vmap(jax.vmap(lambda x, l, u, w: jl.solve_box_qp(x, l, u, w)))(r(xd), r(lo), r(hi), r(W))
    same(jax.tree.map(lambda a: a.reshape((B,) + a.shape[2:]), nested), jl.solve_box_qp(xd, lo, hi, W))
    outer = jax.vmap(lambda x, l, u, w: jl.solve_box_qp(x, l, u, w))(r(xd), r(lo), r(hi), r(W))
    same(jax.tree.map(lambda a: a.reshape((B,) + a.shape[2:]), outer), jl.solve_box_qp(xd, lo, hi, W))
    # the derivative under vmap (grad of each problem) equals the batched derivative
    v = rng.normal(size=(B, n))
    g_map = jax.vmap(jax.grad(lambda x, l, u, w, c: jnp.sum(jl.project_box(x, l, u, w) * c)))(xd, lo, hi, W, v)
    g_all = jax.grad(lambda x: jnp.sum(jl.project_box(x, lo, hi, W) * v))(xd)
    np.testing.assert_allclose(g_map, g_all, rtol=0, atol=1e-10)


def test_vmap_solves_the_mapped_problems_as_one_batch(monkeypatch):
    """The fast path sees the whole mapped batch at once (its blocks, cascade and gathers then apply), not
    one problem at a time lifted by ``vmap`` (every problem then iterates as long as the slowest)."""
    from jaxlimits._src import qp, qp_pdas

    seen = []
    real = qp_pdas.solve

    def spy(x_des, *rest):
        seen.append(x_des.shape)
        return real(x_des, *rest)

    monkeypatch.setattr(qp.qp_pdas, "solve", spy)
    jax.clear_caches()
    rng = np.random.default_rng(32)
    xd, lo, hi, W = _problems(rng, 10, 5, 1e2)
    # (the per-problem function is traced first, for its shapes; the call that runs is the last one traced)
    jax.vmap(lambda x, w: jl.project_box(x, lo[0], hi[0], w))(xd, W)
    assert seen[-1] == (10, 5), seen
    seen.clear()
    jax.vmap(jax.vmap(lambda x, w: jl.project_box(x, lo[0], hi[0], w)))(xd.reshape(2, 5, 5), W.reshape(2, 5, 5, 5))
    assert seen[-1] == (10, 5), seen
    jax.clear_caches()


def _sequential_independent_rows(G, free, cand, eq):
    """Reference for ``qp_active_set._independent_rows`` (float64 NumPy, the rule as documented): the ``eq``
    rows, then the ``cand`` rows in index order, each taken if its free part keeps a norm above
    ``1e3 eps |G_j|`` after modified Gram-Schmidt against the free parts taken before it (an ``eq`` row is
    always taken, and joins the basis if independent)."""
    eps = np.finfo(np.float64).eps
    GF = np.where(free[None, :], G, 0.0)
    basis, take = [], eq.copy()
    for second in (False, True):
        for j in range(G.shape[0]):
            if second and eq[j]:
                continue
            if not second and not eq[j]:
                continue
            v = GF[j].copy()
            for q in basis:
                v = v - (q @ v) * q
            indep = v @ v > (1e3 * eps) ** 2 * (G[j] @ G[j])
            if second:
                take[j] = cand[j] and indep
            if indep and take[j]:
                basis.append(v / np.sqrt(v @ v))
    return take


def test_independent_rows_matches_sequential_gram_schmidt(x64):
    """The robust path's starting working set (a loop since it was unrolled row by row) equals a plain
    sequential reference on rows with exact duplicates, sums of other rows, zero free parts and equalities."""
    from jaxlimits._src.qp_active_set import _independent_rows

    rng = np.random.default_rng(41)
    f = jax.jit(_independent_rows)
    for trial in range(60):
        n, m = int(rng.integers(2, 8)), int(rng.integers(1, 15))
        G = rng.normal(size=(m, n))
        for j in range(1, m):  # duplicates and combinations of earlier rows
            kind = rng.integers(4)
            if kind == 0:
                G[j] = G[rng.integers(j)]
            elif kind == 1 and j >= 2:
                a, b = rng.choice(j, 2, replace=False)
                G[j] = G[a] - 2.0 * G[b]
        free = rng.random(n) < 0.7
        cand, eq = rng.random(m) < 0.7, rng.random(m) < 0.2
        got = np.asarray(f(jnp.asarray(G), jnp.asarray(free), jnp.asarray(cand), jnp.asarray(eq)))
        np.testing.assert_array_equal(got, _sequential_independent_rows(G, free, cand, eq), err_msg=f"trial {trial}")


def test_kkt_solve_program_does_not_grow_with_the_rows():
    """``kkt_solve`` solves for its ``m`` rows' columns at once: its program for 14 rows is not much longer than
    for one (row by row, unrolled, it was ~14x: most of the shield's torque-space QP trace and compile time)."""
    from jaxlimits._src.qp_linalg import kkt_solve

    def eqns(m, n=7, B=4):
        W = jnp.broadcast_to(jnp.eye(n)[..., None], (n, n, B))
        args = (
            W,
            jnp.ones((m, n, B)),
            jnp.ones((n, B), bool),
            jnp.ones((m, B), bool),
            jnp.ones((n, B)),
            jnp.ones((m, B)),
        )
        return len(jax.make_jaxpr(kkt_solve)(*args).eqns)

    one, many = eqns(1), eqns(14)
    assert many < 1.5 * one, (one, many)


@pytest.mark.parametrize("m", [0, 14])
def test_one_problem_runs_the_robust_path_only_when_the_fast_path_leaves_it_unsettled(m):
    """For a batch of one the gather of the one pending problem has a constant index, and XLA hoisted the whole
    robust path out of its loop, running it on every call (the shielded Gymnasium decision: 320 instead of 110 us
    per QP where the fast path had settled it). Behind a ``cond`` it cannot be: no instruction of the robust path
    (``named_scope("robust_path")``) may sit in the compiled program's entry computation, which always runs.
    And the robust path still answers where it is needed (two contradicting rows: infeasible, least violation)."""
    import re

    n = 7
    f = jax.jit(lambda a, lo, up, W, G, h: jl.solve_box_qp(a, lo, up, W, G=G, h=h))
    spec = [jax.ShapeDtypeStruct(s, jnp.float32) for s in ((n,), (n,), (n,), (n, n), (m, n), (m,))]
    text = f.lower(*spec).compile().as_text()
    assert "robust_path" in text  # the scope is there at all (else the check below checks nothing)
    entry = next(c for c in re.split(r"\n(?=\S)", text) if c.startswith("ENTRY"))
    hoisted = [line.strip()[:160] for line in entry.splitlines() if "robust_path" in line]
    assert not hoisted, hoisted

    if m:
        e = np.eye(n, dtype=np.float32)[:1]
        G = np.concatenate([e, -e, np.zeros((m - 2, n), np.float32)])
        h = np.concatenate([[-0.5, -0.5], np.ones(m - 2)]).astype(np.float32)  # x0 <= -0.5 and x0 >= 0.5
        one = np.ones(n, np.float32)
        res = f(np.zeros(n, np.float32), -one, one, np.eye(n, dtype=np.float32), G, h)
        assert bool(res.infeasible) and bool(res.converged)
        np.testing.assert_allclose(float(res.violation), 0.5, atol=1e-5)
