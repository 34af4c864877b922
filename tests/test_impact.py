"""jaxlimits.impact (Wang & Kheddar 2019): formulas vs dense float64 algebra, speed cap vs brute force."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxlimits as jl
from jaxlimits import impact as ji

N = 5
C, DTI, DT = 0.3, 0.005, 0.01


def problem(seed, n=N, batch=None):
    rng = np.random.default_rng(seed)
    shape = () if batch is None else (batch,)
    L = rng.normal(size=shape + (n, n))
    M = L @ np.swapaxes(L, -1, -2) + 0.5 * np.eye(n)
    J = rng.normal(size=shape + (3, n)) * 0.5
    nrm = rng.normal(size=shape + (3,))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    v = rng.normal(size=shape + (n,))
    q = rng.uniform(-1.0, 1.0, size=shape + (n,))
    return M, J, nrm, q, v


LIM = jl.JointLimits(-2.0 * np.ones(N), 2.0 * np.ones(N), 3.0 * np.ones(N), 10.0 * np.ones(N))
TAU = np.linspace(20.0, 60.0, N)


# jitted entry points (eager JAX dispatches op by op, slow on a loaded machine); eager use is tested below
_jump = jax.jit(lambda M, J, n, v, reg: jl.impact_jump(M, J, n, v, C, DTI, reg=reg))
_cap = jax.jit(lambda M, J, n, q, v, reg: jl.impact_speed_cap(M, J, n, q, v, LIM, TAU, DT, C, DTI, reg=reg))
_cons = jax.jit(lambda M, J, n, q, v, reg: jl.impact_constraints(M, J, n, q, v, LIM, TAU, DT, C, DTI, reg=reg))
_meq = jax.jit(lambda M, J, reg: jl.equivalent_mass(M, J, reg=reg))


def dense_jump(M, J, nrm, v, c, dti):
    """Eqs. (3)-(6), (19), (22) written out with explicit inverses, float64."""
    Mi = np.linalg.inv(M)
    Meq = np.linalg.inv(J @ Mi @ J.T)  # (6)
    P = np.outer(nrm, nrm)
    dp = -(1.0 + c) * P @ J @ v  # (4)
    fbar = Meq @ dp / dti  # (5)
    dq = Mi @ J.T @ Meq @ dp  # (22)
    dtau = J.T @ fbar  # (19)
    return dict(w=nrm @ J @ v, dq=dq, dtau=dtau, force=fbar, Meq=Meq, dp=dp)


def dense_ok(M, J, nrm, q, v_bound, dq, dtau, tol=1e-9):
    """(16), (17), (20) checked directly on the jumps (v_bound: the velocity the post-impact one adds to)."""
    pos = np.all(q + DT * dq <= LIM.q_max + tol) and np.all(q + DT * dq >= LIM.q_min - tol)
    vel = np.all(np.abs(v_bound + dq) <= LIM.v_max + tol)
    tau = np.all(np.abs(dtau) <= TAU + tol)
    return pos and vel and tau


def test_jump_matches_dense(dtype):
    M, J, nrm, _, v = problem(1, batch=12)
    out = _jump(*(jnp.asarray(x, dtype) for x in (M, J, nrm, v)), 0.0)
    Meq = _meq(jnp.asarray(M, dtype), jnp.asarray(J, dtype), 0.0)
    assert out.dq.dtype == dtype
    rtol = 1e-9 if dtype == np.float64 else 2e-3
    for i in range(12):
        ref = dense_jump(M[i], J[i], nrm[i], v[i], C, DTI)
        for k in ("w", "dq", "dtau", "force"):
            r = np.asarray(ref[k])
            np.testing.assert_allclose(
                np.asarray(getattr(out, k)[i], np.float64), r, rtol=rtol, atol=rtol * np.max(np.abs(r))
            )
        np.testing.assert_allclose(
            np.asarray(Meq[i], np.float64), ref["Meq"], rtol=rtol, atol=rtol * np.abs(ref["Meq"]).max()
        )
    # the default regularisation changes a well-conditioned answer by ~reg only
    out_reg = _jump(*(jnp.asarray(x, dtype) for x in (M, J, nrm, v)), ji.DEFAULT_REG)
    np.testing.assert_allclose(
        np.asarray(out_reg.dq), np.asarray(out.dq), rtol=1e-3, atol=1e-3 * float(jnp.max(jnp.abs(out.dq)))
    )


def test_jump_identities(x64):
    """J dq is the contact-velocity jump (4) and M dq = dtau dt_imp (the paper's reciprocal of (3))."""
    M, J, nrm, _, v = problem(11)
    out = _jump(M, J, nrm, v, 0.0)
    w = nrm @ J @ v
    np.testing.assert_allclose(J @ np.asarray(out.dq), -(1 + C) * w * nrm, atol=1e-10)
    np.testing.assert_allclose(M @ np.asarray(out.dq), np.asarray(out.dtau) * DTI, atol=1e-10)
    # the jumps grow with c: c_max is the worst case of [c_min, c_max]
    lo = jl.impact_jump(M, J, nrm, v, 0.0, DTI, reg=0.0)
    np.testing.assert_allclose(np.asarray(out.dq), (1 + C) * np.asarray(lo.dq), rtol=1e-12)


def test_constraint_rows_vs_dense(x64):
    """Every row of G a <= h equals the direct post-impact check of (16), (17), (20) at v + a dt."""
    rng = np.random.default_rng(3)
    for seed in range(5):
        M, J, nrm, q, v = problem(100 + seed)
        v = 0.3 * v
        G, h = _cons(M, J, nrm, q, v, 0.0)
        assert G.shape == (6 * N, N) and h.shape == (6 * N,)
        for _ in range(20):
            a = rng.normal(size=N) * 20.0
            v_pre = v + DT * a
            ref = dense_jump(M, J, nrm, v_pre, C, DTI)
            dq, dtau = ref["dq"], ref["dtau"]
            slack_ref = np.concatenate(
                [
                    dq - (LIM.q_max - q) / DT,
                    (LIM.q_min - q) / DT - dq,
                    v_pre + dq - LIM.v_max,
                    -LIM.v_max - v_pre - dq,
                    dtau - TAU,
                    -TAU - dtau,
                ]
            )
            np.testing.assert_allclose(
                np.asarray(G) @ a - np.asarray(h), slack_ref, rtol=1e-8, atol=1e-8 * np.abs(slack_ref).max()
            )


@pytest.mark.parametrize("seed", range(8))
def test_speed_cap_brute_force(seed, x64):
    """The closed-form cap equals the largest feasible w on a fine grid (dense jumps, direct checks)."""
    M, J, nrm, q, v = problem(200 + seed)
    v = 0.2 * v
    out = _cap(M, J, nrm, q, v, 0.0)
    cap = float(out.cap)
    assert cap == pytest.approx(min(float(out.position), float(out.velocity), float(out.torque)))
    # jumps as a function of w (linear, per unit w from a velocity with n^T J v = 1)
    unit = dense_jump(M, J, nrm, J.T @ nrm / (nrm @ J @ J.T @ nrm), C, DTI)
    ws = np.linspace(0.0, 3.0 * cap, 3001)
    feas = np.array([dense_ok(M, J, nrm, q, v, w * unit["dq"], w * unit["dtau"]) for w in ws])
    assert feas[0]
    # feasible exactly on [0, cap]: an interval
    assert np.all(feas[ws <= cap * (1 - 1e-9)])
    assert not np.any(feas[ws >= cap * (1 + 1e-6)])
    assert dense_ok(M, J, nrm, q, v, cap * unit["dq"], cap * unit["dtau"], tol=1e-7)


def test_speed_cap_brute_force_over_joint_velocities(x64):
    """Over random pre-impact joint velocities: the predicted jumps of every one with 0 <= w <= cap
    keep (16), (17), (20), and with w slightly above cap some row fails (the cap is tight)."""
    rng = np.random.default_rng(7)
    M, J, nrm, q, _ = problem(300)
    v_ref = np.zeros(N)
    cap = float(_cap(M, J, nrm, q, v_ref, 0.0).cap)
    for _ in range(300):
        v = rng.normal(size=N)
        w = nrm @ J @ v
        if w <= 0:
            continue
        ref = dense_jump(M, J, nrm, v, C, DTI)
        ok = dense_ok(M, J, nrm, q, v_ref, ref["dq"], ref["dtau"], tol=1e-9)
        assert ok == (w <= cap * (1 + 1e-9)), (w, cap)


def test_v_pre_range_is_conservative(x64):
    rng = np.random.default_rng(5)
    M, J, nrm, q, v = problem(400)
    v = 0.3 * v
    lo, hi = v - 0.2, v + 0.2
    cap_r = float(jl.impact_speed_cap(M, J, nrm, q, v, LIM, TAU, DT, C, DTI, v_pre_range=(lo, hi)).cap)
    vv = rng.uniform(lo, hi, size=(200, N))
    caps = np.asarray(_cap(M, J, nrm, q, vv, ji.DEFAULT_REG).cap)
    assert caps.shape == (200,) and np.all(cap_r <= caps + 1e-12)
    assert cap_r >= 0.5 * caps.min()  # and not vacuous


def test_cap_zero_outside_limits_and_halfspace(x64):
    M, J, nrm, q, v = problem(500)
    v_bad = np.full(N, 4.0)  # beyond v_max = 3
    out = _cap(M, J, nrm, q, v_bad, ji.DEFAULT_REG)
    assert float(out.velocity) == 0.0 and float(out.cap) == 0.0
    cap = 0.2
    G, h = ji.speed_cap_halfspace(M, J, nrm, v, cap, DT)
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.normal(size=N) * 10
        lhs = float((np.asarray(G) @ a - np.asarray(h))[0])
        assert lhs == pytest.approx(nrm @ J @ (v + DT * a) - cap, abs=1e-10)


def test_jit_eager_vmap_batch(x64):
    dtype = np.float64
    M, J, nrm, q, v = problem(700, batch=6)
    args = [jnp.asarray(x, dtype) for x in (M, J, nrm, q, v)]
    f = lambda M, J, n, q, v: jl.impact_speed_cap(M, J, n, q, v, LIM, TAU, DT, C, DTI).cap  # noqa: E731
    eager = f(*args)
    jitted = jax.jit(f)(*args)
    vm = jax.jit(jax.vmap(f))(*args)
    loop = jnp.stack([jax.jit(f)(*(a[i] for a in args)) for i in range(6)])
    tol = 1e-12 if dtype == np.float64 else 1e-5
    for other in (jitted, vm, loop):
        np.testing.assert_allclose(np.asarray(other), np.asarray(eager), rtol=tol)
    G, h = jax.jit(lambda *a: jl.impact_constraints(*a, LIM, TAU, DT, C, DTI))(*args)
    assert G.shape == (6, 6 * N, N) and h.shape == (6, 6 * N) and G.dtype == dtype
    # a single normal shared by the batch broadcasts
    out = jl.impact_jump(args[0], args[1], args[2][0], args[4], C, DTI)
    assert out.dq.shape == (6, N)


def test_gradients(x64):
    M, J, nrm, q, v = problem(800)
    v = 0.2 * v

    def cap(Jx, vx):
        return jl.impact_speed_cap(M, Jx, nrm, q, vx, LIM, TAU, DT, C, DTI).cap

    check_grads(jax.jit(cap), (J, v), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)

    def jump(Mx, Jx):
        return jl.impact_jump(Mx, Jx, nrm, v, C, DTI).dtau

    check_grads(jax.jit(jump), (M, J), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)


def test_singular_no_nan(dtype):
    """Singular contact Jacobians (rank 2, zero, 1e-20 scale): finite values and gradients (the
    regularisation of the module docstring), one batch."""
    M, J, nrm, q, v = problem(900)
    Js = np.stack([J, J, J * 1e-20, J])
    Js[0, 2] = Js[0, 0]
    Js[1] = 0.0
    Js[3, :, 1:] = 0.0  # only joint 0 moves the contact point
    args = [jnp.asarray(x, dtype) for x in (M, Js, nrm, q, v)]

    def total(M, J, n, q, v):
        c = jl.impact_speed_cap(M, J, n, q, v, LIM, TAU, DT, C, DTI)
        jmp = jl.impact_jump(M, J, n, v, C, DTI)
        G, h = jl.impact_constraints(M, J, n, q, v, LIM, TAU, DT, C, DTI)
        return jnp.sum(c.cap) + jnp.sum(jmp.dtau) + jnp.sum(jmp.force) + jnp.sum(G) + jnp.sum(h), c.cap

    (val, cap), grads = jax.jit(jax.value_and_grad(total, argnums=(0, 1, 3, 4), has_aux=True))(*args)
    assert np.isfinite(float(val)) and np.all(np.asarray(cap) >= 0.0) and np.all(np.isfinite(np.asarray(cap)))
    for gr in grads:
        assert np.all(np.isfinite(np.asarray(gr)))
    assert float(cap[1]) > 1e3  # J = 0: no contact-normal motion possible, no jump, no cap (large, finite)


def test_eager_errors():
    M, J, nrm, q, v = problem(0)
    with pytest.raises(ValueError, match="M must be"):
        jl.impact_jump(M[:3], J, nrm, v, C, DTI)
    with pytest.raises(ValueError, match="J must be"):
        jl.impact_jump(M, J[:2], nrm, v, C, DTI)
    with pytest.raises(ValueError, match="normal must be a unit"):
        jl.impact_jump(M, J, 2 * nrm, v, C, DTI)
    with pytest.raises(ValueError, match="c_max"):
        jl.impact_jump(M, J, nrm, v, 1.5, DTI)
    with pytest.raises(ValueError, match="dt_impact"):
        jl.impact_speed_cap(M, J, nrm, q, v, LIM, TAU, DT, C, 0.0)
    with pytest.raises(ValueError, match="dt must"):
        jl.impact_constraints(M, J, nrm, q, v, LIM, TAU, -1.0, C, DTI)
    with pytest.raises(ValueError, match="restitution"):
        ji.check_restitution(0.5, 0.2)
    assert ji.check_restitution(0.0, 0.8) == 0.8
    J6 = np.concatenate([J, np.ones((3, N))])  # (6, n): the linear rows are used
    np.testing.assert_allclose(
        np.asarray(_jump(M, J6, nrm, v, 1e-6).dq), np.asarray(_jump(M, J, nrm, v, 1e-6).dq), rtol=1e-6
    )
