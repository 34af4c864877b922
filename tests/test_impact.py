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


# ---- contact models (impact_contact.py) -------------------------------------------------------------
MODELS = [ji.PaperContact(), ji.CoulombContact(0.0), ji.CoulombContact(0.7)]
MODEL_IDS = ["paper", "frictionless", "coulomb0.7"]


def cone_impulses(rng, nrm, A, w, c, mu, count):
    """Random contact impulses ``p`` (on the wall, ``+n̂`` side) in the friction cone ``|p_t| <= mu p_n`` whose
    normal contact-velocity change is ``-(1 + c) w``: ``n̂^T A p = (1 + c) w``; the joint jump is ``-M^-1 J^T p``.
    Directions on the cone's boundary and inside it."""
    t1 = np.cross(nrm, [1.0, 0.0, 0.0] if abs(nrm[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(nrm, t1)
    out = []
    for _ in range(count):
        phi, r = rng.uniform(0, 2 * np.pi), mu * np.sqrt(rng.uniform()) if rng.uniform() < 0.5 else mu
        d = nrm + r * (np.cos(phi) * t1 + np.sin(phi) * t2)
        nAd = nrm @ A @ d
        if nAd <= 0:
            continue
        out.append((1.0 + c) * w / nAd * d)
    return np.array(out)


def test_frictionless_matches_dense(dtype):
    """CoulombContact(0): the impulse along n̂ with p = (1 + c) w / (n̂^T A n̂), dense float64 algebra."""
    M, J, nrm, _, v = problem(21, batch=8)
    jit = jax.jit(lambda *a: jl.impact_jump(*a, C, DTI, reg=0.0, contact=ji.CoulombContact(0.0)))
    out = jit(*(jnp.asarray(x, dtype) for x in (M, J, nrm, v)))
    assert out.dq.dtype == dtype
    rtol = 1e-9 if dtype == np.float64 else 2e-3
    for i in range(8):
        Mi = np.linalg.inv(M[i])
        A = J[i] @ Mi @ J[i].T
        w = nrm[i] @ J[i] @ v[i]
        p = (1.0 + C) * w / (nrm[i] @ A @ nrm[i]) * nrm[i]
        dq_ref = -Mi @ J[i].T @ p
        np.testing.assert_allclose(
            np.asarray(out.dq[i], np.float64), dq_ref, rtol=rtol, atol=rtol * np.abs(dq_ref).max()
        )
        # the normal contact velocity jumps by -(1 + c) w, the tangential one changes too (unlike the paper's)
        np.testing.assert_allclose(nrm[i] @ J[i] @ dq_ref, -(1 + C) * w, rtol=1e-9)
        np.testing.assert_allclose(
            M[i] @ dq_ref,
            np.asarray(out.dtau[i], np.float64) * DTI,
            rtol=10 * rtol,
            atol=10 * rtol * np.abs(M[i] @ dq_ref).max(),
        )
    assert np.all(np.asarray(out.dq_spread) == 0.0) and np.all(np.asarray(out.dtau_spread) == 0.0)


@pytest.mark.parametrize("mu", [0.3, 1.0])
def test_coulomb_set_contains_every_cone_impulse(mu, x64):
    """Every impulse in the friction cone with the normal restitution law gives a joint jump (and joint impulse)
    inside the model's set theta w (dq_dw ± dq_spread), theta in [0, 1]; the set's ends are reached by some
    impulse to within a factor of 10 (a per-joint box around the cone's image: conservative, not loose by orders),
    except where friction can jam the contact (then the set is unbounded, the cap ~0)."""
    checked = 0
    rng = np.random.default_rng(31)
    for seed in range(6):
        M, J, nrm, _, v = problem(600 + seed)
        jump = jl.impact_jump(M, J, nrm, v, C, DTI, reg=0.0, contact=ji.CoulombContact(mu))
        w = float(jump.w)
        if w <= 0:
            v, w = -v, -w
            jump = jl.impact_jump(M, J, nrm, v, C, DTI, reg=0.0, contact=ji.CoulombContact(mu))
        A = J @ np.linalg.inv(M) @ J.T
        jammed = nrm @ A @ nrm <= mu * np.linalg.norm((np.eye(3) - np.outer(nrm, nrm)) @ A @ nrm)
        for c in (0.0, C):
            ps = cone_impulses(rng, nrm, A, w, c, mu, 400)
            dq = -np.linalg.solve(M, J.T @ ps.T).T  # (k, n)
            dtau = -(J.T @ ps.T).T / DTI
            for val, mid, spread in ((dq, jump.dq_dw, jump.dq_spread), (dtau, jump.dtau_dw, jump.dtau_spread)):
                hi = np.maximum(0.0, w * (np.asarray(mid) + np.asarray(spread)))
                lo = np.minimum(0.0, w * (np.asarray(mid) - np.asarray(spread)))
                tol = 1e-9 * np.abs(val).max()
                assert np.all(val <= hi + tol) and np.all(val >= lo - tol)
                if c == C and not jammed:  # not vacuous: the sampled impulses use a good part of the box
                    used = np.maximum(val.max(0) / np.maximum(hi, 1e-300), val.min(0) / np.minimum(lo, -1e-300))
                    assert np.all(used > 0.1), used
                    checked += 1
    assert checked >= 4  # most of the random problems do not jam


def _cap_fn(contact):
    return jax.jit(
        lambda M, J, n, q, v: jl.impact_speed_cap(M, J, n, q, v, LIM, TAU, DT, C, DTI, reg=0.0, contact=contact)
    )


@pytest.mark.parametrize("mu", [0.0, 0.5])
def test_coulomb_cap_brute_force(mu, x64):
    """Below the cap every cone impulse keeps (16), (17), (20); mu = 0 (exact): just above it some row fails."""
    rng = np.random.default_rng(41)
    cap_f = _cap_fn(ji.CoulombContact(mu))
    for seed in range(6):
        M, J, nrm, q, v = problem(700 + seed)
        v = 0.2 * v
        cap = float(cap_f(M, J, nrm, q, v).cap)
        assert np.isfinite(cap) and cap >= 0.0
        A = J @ np.linalg.inv(M) @ J.T
        for w in (0.5 * cap, cap * (1 - 1e-9)):
            ps = cone_impulses(rng, nrm, A, w, C, mu, 300)
            for p in ps:
                dq = -np.linalg.solve(M, J.T @ p)
                assert dense_ok(M, J, nrm, q, v, dq, -J.T @ p / DTI, tol=1e-7)
        if mu == 0.0 and cap > 0:
            p = (1 + C) * cap * 1.001 / (nrm @ A @ nrm) * nrm
            assert not dense_ok(M, J, nrm, q, v, -np.linalg.solve(M, J.T @ p), -J.T @ p / DTI, tol=1e-9)


def test_coulomb_cap_shrinks_with_friction_and_jams(x64):
    """More friction, a wider set: the cap does not grow with mu; where friction can jam the contact
    (n̂^T A n̂ <= mu |P_t A n̂|) the normal impulse is unbounded and the cap is ~0, finite."""
    M, J, nrm, q, v = problem(800)
    v = 0.1 * v
    caps = [float(_cap_fn(ji.CoulombContact(mu))(M, J, nrm, q, v).cap) for mu in (0.0, 0.2, 0.5, 1.0)]
    assert all(b <= a * (1 + 1e-12) for a, b in zip(caps, caps[1:])), caps
    A = J @ np.linalg.inv(M) @ J.T
    P = np.eye(3) - np.outer(nrm, nrm)
    mu_jam = 1.01 * (nrm @ A @ nrm) / np.linalg.norm(P @ A @ nrm)
    cap = float(_cap_fn(ji.CoulombContact(mu_jam))(M, J, nrm, q, v).cap)
    assert np.isfinite(cap) and 0.0 <= cap < 1e-6


def test_coulomb_constraint_rows_vs_direct(x64):
    """With a spread, G a <= h holds exactly when both ends of the set satisfy (16), (17), (20) at v + a dt."""
    rng = np.random.default_rng(9)
    contact = ji.CoulombContact(0.6)
    M, J, nrm, q, v = problem(900)
    v = 0.3 * v
    G, h = jl.impact_constraints(M, J, nrm, q, v, LIM, TAU, DT, C, DTI, reg=0.0, contact=contact)
    assert G.shape == (12 * N, N) and h.shape == (12 * N,)
    for _ in range(40):
        a = rng.normal(size=N) * 20.0
        v_pre = v + DT * a
        jmp = jl.impact_jump(M, J, nrm, v_pre, C, DTI, reg=0.0, contact=contact)
        w = float(jmp.w)
        ok = True
        for sgn in (1.0, -1.0):
            dq = w * (np.asarray(jmp.dq_dw) + sgn * np.asarray(jmp.dq_spread))
            dtau = w * (np.asarray(jmp.dtau_dw) + sgn * np.asarray(jmp.dtau_spread))
            ok &= dense_ok(M, J, nrm, q, v_pre, dq, dtau, tol=0.0)
        assert ok == bool(np.all(np.asarray(G) @ a <= np.asarray(h)))


@pytest.mark.parametrize("contact", MODELS, ids=MODEL_IDS)
def test_contact_models_jit_vmap_grad_singular(contact, dtype):
    """Every contact model: jit = eager = vmap, the dtype kept, finite values and gradients also at singular
    Jacobians (rank 2, zero, 1e-20 scale)."""
    M, J, nrm, q, v = problem(1000, batch=4)
    J = J.copy()
    J[0, 2] = J[0, 0]
    J[1] = 0.0
    J[2] *= 1e-20
    args = [jnp.asarray(x, dtype) for x in (M, J, nrm, q, v)]

    def total(M, J, n, q, v):
        c = jl.impact_speed_cap(M, J, n, q, v, LIM, TAU, DT, C, DTI, contact=contact)
        G, h = jl.impact_constraints(M, J, n, q, v, LIM, TAU, DT, C, DTI, contact=contact)
        return jnp.sum(c.cap) + jnp.sum(G) + jnp.sum(h), c.cap

    eager = total(*args)[1]
    jitted = jax.jit(total)(*args)[1]
    vm = jax.jit(jax.vmap(total))(*args)[1]
    assert eager.dtype == dtype and np.all(np.isfinite(np.asarray(eager))) and np.all(np.asarray(eager) >= 0)
    tol = 1e-10 if dtype == np.float64 else 1e-4
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=tol)
    np.testing.assert_allclose(np.asarray(vm), np.asarray(eager), rtol=tol)
    grads = jax.jit(jax.grad(lambda *a: total(*a)[0], argnums=(0, 1, 3, 4)))(*args)
    for gr in grads:
        assert np.all(np.isfinite(np.asarray(gr)))


def test_coulomb_gradients(x64):
    M, J, nrm, q, v = problem(1100)
    v = 0.2 * v

    def cap(Jx, vx):
        return jl.impact_speed_cap(M, Jx, nrm, q, vx, LIM, TAU, DT, C, DTI, contact=ji.CoulombContact(0.4)).cap

    check_grads(jax.jit(cap), (J, v), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)


def test_contact_model_errors():
    M, J, nrm, q, v = problem(0)
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="mu must be"):
            ji.CoulombContact(bad)
    with pytest.raises(ValueError, match="contact must be a ContactModel"):
        jl.impact_jump(M, J, nrm, v, C, DTI, contact="paper")
    with pytest.raises(ValueError, match="contact must be a ContactModel"):
        jl.ImpactCap(M, J, nrm, LIM, 50.0, DT, C, DTI, contact=0.5)
    # the paper's model stays the default: the defaults reproduce it
    np.testing.assert_array_equal(
        np.asarray(jl.impact_jump(M, J, nrm, v, C, DTI).dq),
        np.asarray(jl.impact_jump(M, J, nrm, v, C, DTI, contact=ji.PaperContact()).dq),
    )


# ---- the braking-robust cap row (speed_cap_halfspace(..., box=)) -------------------------------------------------
def _braking_case(seed, batch=64):
    M, J, nrm, q, v = problem(seed, batch=batch)
    rng = np.random.default_rng(seed + 1)
    lower = rng.uniform(-20.0, 5.0, size=(batch, N))
    upper = lower + rng.uniform(0.0, 25.0, size=(batch, N))
    upper[:, 0] = lower[:, 0]  # a pinned joint (lower == upper): its term is a constant
    return M, J, nrm, v, lower, upper


def test_braking_row_implies_the_braked_speeds_and_meets_the_box_when_they_can(x64):
    """Brute force over the box: every acceleration the row admits leaves sum_i max(0, g_i v+_i) <= cap, so
    every velocity between the end-of-step one and rest (joints braked in any subset) approaches at most at the
    cap, and the one-step row holds too; at the box's corners the row is the exact constraint (tight); its minimum
    over the box equals the exact constraint's (the same states are infeasible); where every joint's term stays
    >= 0 on the box it is the one-step row."""
    M, J, nrm, v, lower, upper = _braking_case(900)
    cap = 0.4
    G, h = ji.speed_cap_halfspace(M, J, nrm, v, cap, DT, box=(lower, upper))
    G, h = np.asarray(G)[:, 0], np.asarray(h)[:, 0]
    g = np.einsum("bin,bi->bn", J, nrm)
    rng = np.random.default_rng(3)
    admitted = 0
    for b in range(len(v)):
        a = rng.uniform(lower[b], upper[b], size=(4000, N))
        a[:64] = np.where(rng.random((64, N)) < 0.5, lower[b], upper[b])  # corners
        # the chords touch max(0, x_i) at both ends of x_i's range: exact at the box's corners (tight, not just safe)
        xc = g[b] * (v[b] + DT * a[:64])
        np.testing.assert_allclose(a[:64] @ G[b] - h[b], np.maximum(xc, 0.0).sum(-1) - cap, atol=1e-9)
        ok = a @ G[b] <= h[b]
        x = g[b] * (v[b] + DT * a[ok])
        assert np.all(np.maximum(x, 0.0).sum(-1) <= cap + 1e-9)
        assert np.all(x.sum(-1) <= cap + 1e-9)
        # braking any subset of joints to rest (or part way) keeps it: sampled scalings in [0, 1] per joint
        s = rng.random(x.shape)
        assert np.all((s * x).sum(-1) <= cap + 1e-9)
        admitted += int(ok.sum())
        x_lo = np.minimum(g[b] * (v[b] + DT * lower[b]), g[b] * (v[b] + DT * upper[b]))
        row_min = np.sum(np.where(G[b] > 0, lower[b], upper[b]) * G[b]) - h[b]
        assert row_min == pytest.approx(np.maximum(x_lo, 0.0).sum() - cap, abs=1e-9)
    assert admitted > 10_000  # not vacuous
    # all terms positive on the box: the one-step row
    v_pos = np.abs(v) * np.sign(g) + 3.0 * np.sign(g)
    lo_s, hi_s = -np.ones_like(v), np.ones_like(v)
    G1, h1 = ji.speed_cap_halfspace(M, J, nrm, v_pos, cap, DT)
    G2, h2 = ji.speed_cap_halfspace(M, J, nrm, v_pos, cap, DT, box=(lo_s, hi_s))
    np.testing.assert_allclose(np.asarray(G2), np.asarray(G1), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(h2), np.asarray(h1), rtol=1e-12, atol=1e-12)


def test_braking_row_jit_vmap_dtype_and_gradients(dtype):
    M, J, nrm, v, lower, upper = _braking_case(901, batch=8)
    args = [jnp.asarray(x, dtype) for x in (M, J, nrm, v, lower, upper)]

    def f(M, J, n, v, lo, hi):
        return ji.speed_cap_halfspace(M, J, n, v, 0.3, DT, box=(lo, hi))

    G, h = f(*args)
    Gj, hj = jax.jit(f)(*args)
    Gv, hv = jax.jit(jax.vmap(f))(*args)
    assert G.shape == (8, 1, N) and h.shape == (8, 1) and G.dtype == dtype and h.dtype == dtype
    tol = 1e-12 if dtype == np.float64 else 1e-5
    for Go, ho in ((Gj, hj), (Gv, hv)):
        np.testing.assert_allclose(np.asarray(Go), np.asarray(G), rtol=tol, atol=tol)
        np.testing.assert_allclose(np.asarray(ho), np.asarray(h), rtol=tol, atol=tol)
    grad = jax.grad(lambda v: jnp.sum(f(args[0], args[1], args[2], v, args[4], args[5])[1]))(args[3])
    assert np.all(np.isfinite(np.asarray(grad)))
