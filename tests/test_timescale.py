"""Time-scaled IK (Suleiman et al. (15)-(22)) against an independent solver: SciPy SLSQP on the full QP."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize

import jaxlimits as jl
from jaxlimits._src.timescale import householder_qr


def _random(rng, B, m, n, scale=1.0):
    J = rng.normal(size=(B, m, n))
    dr = rng.normal(size=(B, m)) * scale
    return J, dr


B, M, N = 16, 2, 3  # one problem structure for every float64 test (each new one costs a compilation)
A_ROW = np.ones((1, N))  # an extra rate row: |q1' + q2' + q3'| <= 0.9
V_MAX, B_MAX = 0.5, 0.9


def _solve(J, dr, dq_min, dq_max, **kw):
    return jl.timescale_ik(J, dr, V_MAX, dq_min=dq_min, dq_max=dq_max, A=A_ROW, b_min=-B_MAX, b_max=B_MAX, **kw)


def _slsqp(J, dr, alpha, t_lo, w, dq_min, dq_max, t_fix=None):
    """The full problem (15)/(18) in (dq, T), float64, SLSQP from a least-squares start."""
    m, n = J.shape
    W = np.diag(np.append(w, 0.0 if t_fix is not None else alpha))
    E = np.eye(n)
    z = np.zeros((n, 1))
    cons = [dict(type="eq", fun=lambda x: J @ x[:n] - dr, jac=lambda x: np.hstack([J, np.zeros((m, 1))]))]
    for s in (1.0, -1.0):
        cons.append(
            dict(
                type="ineq",
                fun=lambda x, s=s: V_MAX * x[n] - s * x[:n],
                jac=lambda x, s=s: np.hstack([-s * E, np.full((n, 1), V_MAX)]),
            )
        )
        cons.append(
            dict(
                type="ineq",
                fun=lambda x, s=s: B_MAX * x[n] - s * (A_ROW @ x[:n]),
                jac=lambda x, s=s: np.hstack([-s * A_ROW, [[B_MAX]]]),
            )
        )
    cons.append(dict(type="ineq", fun=lambda x: dq_max - x[:n], jac=lambda x: np.hstack([-E, z])))
    cons.append(dict(type="ineq", fun=lambda x: x[:n] - dq_min, jac=lambda x: np.hstack([E, z])))
    lo = t_lo if t_fix is None else t_fix
    dq0 = np.linalg.lstsq(J, dr, rcond=None)[0]
    x0 = np.append(
        dq0, max(lo, np.max(np.abs(dq0)) / V_MAX, abs(A_ROW @ dq0).max() / B_MAX) if t_fix is None else t_fix
    )
    bounds = [(None, None)] * n + [(lo, None if t_fix is None else t_fix)]
    r = minimize(
        lambda x: x @ W @ x,
        x0,
        jac=lambda x: 2 * W @ x,
        constraints=cons,
        bounds=bounds,
        method="SLSQP",
        options=dict(ftol=1e-15, maxiter=500),
    )
    assert r.success, r.message
    return r.x[:n], r.x[n], r.fun


def _problems(seed, scale=1.0):
    rng = np.random.default_rng(seed)
    J, dr = _random(rng, B, M, N, scale)
    # position bounds: wide for half of the problems, binding for the others
    width = np.where(np.arange(B)[:, None] % 2 == 0, 100.0, 1.0)
    return J, dr, -rng.uniform(0.3, 1.0, (B, N)) * width, rng.uniform(0.3, 1.0, (B, N)) * width


def test_matches_slsqp_on_random_problems(x64):
    J, dr, dq_min, dq_max = _problems(0)
    alpha, t_min = 0.5, 0.05
    w = np.random.default_rng(10).uniform(0.5, 2.0, N)
    res = _solve(J, dr, dq_min, dq_max, t_min=t_min, alpha=alpha, weights=w, r_dot_max=2.0)
    assert res.dq.shape == (B, N) and res.t.shape == (B,)
    checked = 0
    for b in range(B):
        t_lo = max(t_min, np.max(np.abs(dr[b])) / 2.0)
        try:
            dq_ref, t_ref, f_ref = _slsqp(J[b], dr[b], alpha, t_lo, w, dq_min[b], dq_max[b])
        except AssertionError:
            assert not res.reached[b]  # SLSQP finds no feasible point: neither may we claim one
            continue
        assert res.reached[b]
        checked += 1
        dq, t = np.asarray(res.dq[b]), float(res.t[b])
        assert dq @ (w * dq) + alpha * t * t == pytest.approx(f_ref, rel=1e-6)
        np.testing.assert_allclose(dq, dq_ref, atol=1e-5 * (1 + np.abs(dq_ref).max()))
        assert t == pytest.approx(t_ref, rel=1e-5)
    assert checked >= B // 2
    # the claims, on every problem reached; the limits on all of them
    ok = np.asarray(res.reached)
    dq, t = np.asarray(res.dq), np.asarray(res.t)
    resid = np.einsum("bmn,bn->bm", J, dq) - dr
    assert np.max(np.abs(resid[ok])) < 1e-12
    assert np.all(np.abs(dq) <= V_MAX * t[:, None] * (1 + 1e-12))
    assert np.all(np.abs(dq @ A_ROW.T)[:, 0] <= B_MAX * t * (1 + 1e-12))
    assert np.all(t >= t_min)
    assert np.all((dq >= dq_min) & (dq <= dq_max))
    assert np.all(np.max(np.abs(dr), -1) <= 2.0 * t * (1 + 1e-12))
    assert np.any(~ok) and np.all(res.converged)


def test_claims_hold_in_both_dtypes_with_rounding(dtype):
    J, dr, dq_min, dq_max = _problems(2, 0.02)
    dq_min, dq_max = 100 * np.abs(dq_min) * -1, 100 * np.abs(dq_max)
    dr[::2] *= 0.05  # small displacements: t_min decides (one period)
    t_s = 5e-3
    cast = [a.astype(dtype) for a in (J, dr, dq_min, dq_max)]
    res = _solve(*cast, t_min=t_s, alpha=1.0, r_norm_max=0.7, t_step=t_s)
    assert res.dq.dtype == dtype and res.t.dtype == dtype
    for a in res:
        assert np.all(np.isfinite(np.asarray(a)))
    eps = np.finfo(dtype).eps
    dq, t, t_opt, steps = (np.asarray(a, np.float64) for a in (res.dq, res.t, res.t_opt, res.steps))
    assert np.all(res.reached) and np.all(res.converged)
    assert np.max(np.abs(np.einsum("bmn,bn->bm", J, dq) - dr)) < 200 * eps * np.max(np.abs(dr))
    assert np.all(np.abs(dq) <= V_MAX * t_opt[:, None] * (1 + 8 * eps))
    assert np.all(np.linalg.norm(dr, axis=-1) <= 0.7 * t_opt * (1 + 8 * eps))
    assert np.all(t_opt >= t_s * (1 - eps))
    # eq. 22: (n - 1) T_s <= T <= n T_s, and t = n T_s
    assert np.all(steps >= 1)
    assert np.all(((steps - 1) * t_s <= t_opt * (1 + 4 * eps)) & (t_opt <= steps * t_s * (1 + 4 * eps)))
    np.testing.assert_allclose(t, steps * t_s, rtol=4 * eps)
    assert np.any(steps > 1) and np.any(steps == 1)
    # float32 agrees with float64 to float32 accuracy
    with jax.enable_x64(True):  # (the rounding is outside the compiled solver: no new compilation)
        ref = _solve(J, dr, dq_min, dq_max, t_min=t_s, alpha=1.0, r_norm_max=0.7)
    np.testing.assert_allclose(t_opt, np.asarray(ref.t_opt), rtol=1e3 * eps)


def _singular_problems():
    rng = np.random.default_rng(3)
    J, dr, lo, hi = _problems(3, 0.05)
    lo, hi = -np.ones((B, N)), np.ones((B, N))
    for k in range(4):
        a = rng.normal(size=N)
        J[k] = np.stack([a, 2 * a])  # rank one, dr off its range: least squares, flagged
        dr[k] = np.array([0.1, -0.1])
    J[0] = 0.0  # J = 0 entirely
    for k in range(4, 8):  # position bounds too tight for dr: the limits win, flagged
        dr[k] = np.array([5.0, -5.0])
        lo[k], hi[k] = -0.01, 0.01
    return J, dr, lo, hi


def test_singular_and_unreachable_are_flagged_never_nan(x64):
    J, dr, lo, hi = _singular_problems()
    res = _solve(J, dr, lo, hi, t_min=1e-3)
    for a in res:
        assert np.all(np.isfinite(np.asarray(a)))
    assert not np.any(res.reached[:8]) and np.all(res.reached[8:])
    dq, t = np.asarray(res.dq), np.asarray(res.t)
    assert np.all((dq >= lo) & (dq <= hi))
    assert np.all(np.abs(dq) <= V_MAX * t[:, None] * (1 + 1e-12)) and np.all(t >= 1e-3)
    np.testing.assert_allclose(dq[0], 0.0, atol=1e-12)
    # rank one: the least-squares motion (J dq is the projection of dr on the range of J)
    u = np.array([1.0, 2.0]) / np.sqrt(5.0)
    for k in (1, 2, 3):
        np.testing.assert_allclose(J[k] @ dq[k], u * (u @ dr[k]), atol=1e-8)


def test_gradients_match_finite_differences_and_are_finite_when_flagged(x64):
    J, dr, lo, hi = _problems(4, 0.05)
    lo, hi = -np.ones((B, N)), np.ones((B, N))

    def f(J, dr):
        r = _solve(J, dr, lo, hi, t_min=1e-3, alpha=0.3)
        return jnp.concatenate([r.dq, r.t[:, None]], -1)

    r = _solve(J, dr, lo, hi, t_min=1e-3, alpha=0.3)
    assert np.all(r.t > 2e-3)  # the velocity rows decide T (not t_min)
    rng = np.random.default_rng(11)
    # reverse mode (the transpose of the custom JVP) against central differences in 3 directions
    y, vjp = jax.vjp(f, J, dr)
    u = rng.normal(size=y.shape)
    gJ, gdr = vjp(u)
    eps = 1e-6
    for _ in range(3):
        dJ, ddr = rng.normal(size=J.shape), rng.normal(size=dr.shape)
        fd = (f(J + eps * dJ, dr + eps * ddr) - f(J - eps * dJ, dr - eps * ddr)) / (2 * eps)
        lhs = float(np.sum(u * np.asarray(fd)))
        rhs = float(np.sum(np.asarray(gJ) * dJ) + np.sum(np.asarray(gdr) * ddr))
        assert rhs == pytest.approx(lhs, rel=1e-5, abs=1e-8)
    # finite at the singular and unreachable problems
    Js, drs, los, his = _singular_problems()

    def fs(J, dr):
        r = _solve(J, dr, los, his, t_min=1e-3, alpha=0.3)
        return jnp.concatenate([r.dq, r.t[:, None]], -1)

    ys, vjp = jax.vjp(fs, Js, drs)
    assert np.all(np.isfinite(np.asarray(ys)))
    g = vjp(jnp.ones_like(ys))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)


def test_jit_of_vmap_agrees_with_eager(x64):
    J, dr, lo, hi = _problems(5, 0.05)

    def f(J, dr, lo, hi):
        return _solve(J, dr, lo, hi, t_min=1e-3, r_dot_max=0.7)

    e = f(J, dr, lo, hi)
    v = jax.jit(jax.vmap(f))(J, dr, lo, hi)
    for a, c in zip(e, v):
        np.testing.assert_allclose(np.asarray(a, np.float64), np.asarray(c, np.float64), rtol=1e-12, atol=1e-14)


def test_fixed_time_ik_is_conventional_ik(x64):
    J, dr, lo, hi = _problems(6, 0.01)
    res = jl.fixed_time_ik(J, dr, 0.01, V_MAX, dq_min=lo, dq_max=hi, A=A_ROW, b_min=-B_MAX, b_max=B_MAX)
    assert np.all(np.asarray(res.t) == 0.01)
    feasible = 0
    for b in range(B):
        speed = np.max(np.abs(np.asarray(res.dq[b]))) / 0.01
        try:
            dq_ref, _, _ = _slsqp(J[b], dr[b], 0.0, 0.0, np.ones(N), lo[b], hi[b], t_fix=0.01)
        except AssertionError:
            assert speed > V_MAX  # (5) infeasible: the equality is kept, the limits are not
            assert res.reached[b]
            continue
        feasible += 1
        np.testing.assert_allclose(np.asarray(res.dq[b]), dq_ref, atol=1e-7)
        assert speed <= V_MAX * (1 + 1e-9)
    assert 0 < feasible < B


def test_householder_qr_is_a_qr():
    A = np.random.default_rng(7).normal(size=(5, 2)).astype(np.float32)
    Q, R = householder_qr(jnp.asarray(A))
    np.testing.assert_allclose(np.asarray(Q) @ np.vstack([np.asarray(R), np.zeros((3, 2))]), A, atol=1e-5)
    np.testing.assert_allclose(np.asarray(Q).T @ np.asarray(Q), np.eye(5), atol=1e-5)
    assert np.allclose(np.tril(np.asarray(R), -1), 0.0, atol=1e-5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(J=np.ones((3, 2)), dr=np.ones(3)), "m <= n"),
        (dict(J=np.ones((2, 4)), dr=np.ones(3)), "shape"),
        (dict(v_max=0.0), "v_max"),
        (dict(t_min=-1.0), "t_min"),
        (dict(alpha=0.0), "alpha"),
        (dict(weights=np.array([1.0, 1.0, -1.0, 1.0])), "weights"),
        (dict(r_dot_max=0.0), "r_dot_max"),
        (dict(t_step=0.0), "t_step"),
        (dict(dq_min=np.full(4, 0.1), dq_max=np.ones(4)), "dq_min"),
        (dict(dq_min=-np.ones(4)), "both"),
        (dict(dr=np.array([np.nan, 0.0])), "dr"),
    ],
)
def test_bad_inputs_raise_eagerly(kwargs, match):
    args = dict(J=np.ones((2, 4)), dr=np.ones(2), v_max=0.5)
    args.update(kwargs)
    J, dr, v = args.pop("J"), args.pop("dr"), args.pop("v_max")
    with pytest.raises(ValueError, match=match):
        jl.timescale_ik(J, dr, v, **args)
