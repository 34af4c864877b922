"""Checks that close gaps a mutation audit found (``benchmarks/mutation_audit.py``): plausible bugs that
passed every other test.

* the size of the rounding guard, in float64 (a few ulps) and float32 (as documented);
* gradients with ``rounding_guard=False`` at states exactly on the limits the formulas use;
* the values of the conflict rule (which braking action a non-viable state gets), against a
  brute-force per-side reference.

Public API only (``import jaxlimits as jl``); the references are independent simulations.
"""

from __future__ import annotations

import math
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

import jaxlimits as jl  # noqa: E402
import semi_implicit_reference as sir  # noqa: E402
from jerk_reference import JLimits1, braking_peak_dense, position_threshold_dense  # noqa: E402

# (q_min, q_max, v_max, a_max), dt, integrator, substeps
CONFIGS = [
    ((-2.0, 2.0, 2.0, 12.0), 0.01, "zoh", 1),
    ((-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 5),
    ((-0.3, 1.7, 1.5, 20.0), 0.02, "semi_implicit", 10),
    ((-0.05, 0.05, 1.0, 9.998), 0.1, "zoh", 1),  # condition (11) within 0.02 % of equality
    ((-0.5, 0.5, 2.0, 10.0), 0.1, "semi_implicit", 4),
]


def _id(cfg):
    lim, dt, integrator, n = cfg
    return f"{integrator}{n}-span{lim[1] - lim[0]:g}-dt{dt:g}"


# ----------------------------------------------------------------------------- 1. the rounding guard's size


def documented_roundings(lim, dt, integrator, substeps):
    """``R = 2 + substeps (1 + ceil(v_max / (a_max dt)))`` of ``acc_bounds``' rounding guard (zoh: 3 per step)."""
    _, _, v_max, a_max = lim
    per_step = 3 if integrator == "zoh" else substeps
    return 2 + per_step * (1 + math.ceil(v_max / (a_max * dt)))


def narrowed_limits(lim, dtype, roundings):
    """The limits the guard documents, rounded as the state's dtype holds them: positions in by
    ``R eps (max|q_lim| + 2 v_max^2 / a_max)``, ``v_max (1 - R eps)``."""
    q_min, q_max, v_max, a_max = (dtype(x) for x in lim)
    eps = dtype(np.finfo(dtype).eps) * dtype(roundings)
    m_q = eps * (max(abs(q_min), abs(q_max)) + dtype(2) * v_max * v_max / a_max)
    return jl.JointLimits(*(float(x) for x in (q_min + m_q, q_max - m_q, v_max * (dtype(1) - eps), a_max)))


def guard_states(lim, dt, dtype):
    """States where each guarded limit binds: at rest close to a limit (position and viability), mid-range
    just below the velocity limit, and moving toward a limit a little inside the braking curve."""
    q_min, q_max, v_max, a_max = lim
    u = np.linspace(0.05, 0.4, 8)
    d_rest = a_max * dt * dt * u
    v_fast = v_max - a_max * dt * (0.1 + 0.8 * u)
    v_curve = v_max * (0.2 + 2.0 * u)
    d_curve = v_curve**2 / (2 * a_max) * 1.3 + a_max * dt * dt
    mid = 0.5 * (q_min + q_max)
    q = np.concatenate([q_max - d_rest, q_min + d_rest, mid + 0 * u, mid + 0 * u, q_max - d_curve, q_min + d_curve])
    v = np.concatenate([0 * u, 0 * u, v_fast, -v_fast, v_curve, -v_curve])
    return q.astype(dtype), v.astype(dtype)


@pytest.mark.parametrize("cfg", CONFIGS, ids=[_id(c) for c in CONFIGS])
def test_rounding_guard_is_the_documented_narrowing(cfg, dtype):
    """``rounding_guard=True`` is the exact bound for the limits narrowed by the documented ``R`` roundings of
    the state's dtype (``jl.acc_bounds`` docstring and its ``_rounding_guard``): computed here in float64 from
    the formula, it matches the guarded bounds far better than ``R - 1`` or ``R + 1`` roundings would."""
    lim, dt, integrator, n = cfg
    q, v = guard_states(lim, dt, dtype)
    kw = dict(integrator=integrator, substeps=n)
    got = jl.acc_bounds(q, v, jl.JointLimits(*lim), dt, **kw)
    got = np.stack([np.asarray(got.lower, np.float64), np.asarray(got.upper, np.float64)])
    R = documented_roundings(lim, dt, integrator, n)
    err = {}
    with jax.enable_x64(True):
        for r in (R - 1, R, R + 1):
            ref = jl.acc_bounds(
                q.astype(np.float64),
                v.astype(np.float64),
                narrowed_limits(lim, dtype, r),
                dt,
                rounding_guard=False,
                **kw,
            )
            err[r] = float(np.max(np.abs(got - np.stack([np.asarray(ref.lower), np.asarray(ref.upper)]))))
    a_max = lim[3]
    # float32: the formulas' own rounding (~1e-6 a_max on the braking curve); one rounding more or less moves
    # the bounds near a limit by ~2 R^-1 of the margin over dt^2, several times that
    assert err[R] <= (5e-6 if dtype == np.float32 else 1e-12) * a_max, err
    assert err[R] <= 0.5 * min(err[R - 1], err[R + 1]), err


@pytest.mark.parametrize("cfg", CONFIGS, ids=[_id(c) for c in CONFIGS])
def test_float64_rounding_guard_moves_the_bounds_by_ulps(cfg, x64):
    """In float64 the guard is ~1e-13 rad of range: on random and near-limit states the bounds with and without
    it differ by at most 1e-8 a_max (the largest, ~1e-9 a_max, where the bound is steepest in the distance to a
    limit: ``1 / h^2`` at the first semi-implicit substep, ``v^2 / (2 d^2)`` at the zero-order hold's vertex),
    and by nothing at all on most states. A guard sized with float32's eps moves them by ~1e-3 rad/s^2."""
    lim, dt, integrator, n = cfg
    q_min, q_max, v_max, a_max = lim
    rng = np.random.default_rng(13)
    m = 2000
    d = (q_max - q_min) * rng.uniform(size=m) ** 4
    v = v_max * rng.uniform(-1, 1, m)
    side = rng.choice([-1.0, 1.0], m)
    q = np.concatenate([rng.uniform(q_min, q_max, m), np.where(side > 0, q_max - d, q_min + d)])
    v = np.concatenate([v_max * rng.uniform(-1, 1, m), side * v])
    kw = dict(integrator=integrator, substeps=n)
    lim_ = jl.JointLimits(*lim)
    guarded = jl.acc_bounds(q, v, lim_, dt, **kw)
    bare = jl.acc_bounds(q, v, lim_, dt, rounding_guard=False, **kw)
    viable = np.asarray(bare.viable)
    assert viable.sum() > m
    diff = np.maximum(
        np.abs(np.asarray(guarded.lower) - np.asarray(bare.lower)),
        np.abs(np.asarray(guarded.upper) - np.asarray(bare.upper)),
    )[viable]
    assert np.max(diff) <= 1e-8 * a_max, np.max(diff)
    assert np.percentile(diff, 90) <= 1e-11 * a_max, np.percentile(diff, 90)
    assert np.count_nonzero(diff > 0) > 0  # the guard does act


# ----------------------------------------------------------------------------- 2. gradients on the exact limits


GRAD_LIM = (-2.0, 2.0, 2.0, 12.0, 200.0)  # q_min, q_max, v_max, a_max, j_max
GRAD_DT = 0.01
GRAD_MODELS = [("zoh", 1), ("semi_implicit", 1), ("semi_implicit", 5)]


def model_braking_distance(v, a_max, integrator, h):
    """The braking distance of the model (independent: zoh ``v^2 / (2 a_max)``, semi-implicit summed)."""
    v = np.asarray(v, np.float64)
    if integrator == "zoh":
        return np.maximum(v, 0.0) ** 2 / (2.0 * a_max)
    return sir.braking_distance(v, a_max, h)


def limit_states(integrator, n):
    """(q, v, a_prev) exactly on the limits the formulas use, and just outward of them."""
    q_min, q_max, v_max, a_max, _ = GRAD_LIM
    rows = [
        (q_max, 0.0),
        (q_min, 0.0),
        (q_max, -v_max),
        (q_min, v_max),
        (0.0, v_max),
        (0.0, -v_max),
        (0.5, v_max),
        (-0.5, -v_max),
    ]
    for v in (1e-6, 0.5, v_max, 1.5 * v_max, 3 * v_max):  # on a limit, moving out (at and past v_max)
        rows += [(q_max, v), (q_min, -v)]
    for dq, v in ((1e-7, 0.0), (1e-3, 0.5), (0.5, v_max), (1e-3, -0.5)):  # past a limit
        rows += [(q_max + dq, v), (q_min - dq, -v)]
    for v in (0.1, 1.0, v_max):  # exactly on the model's viability curve, and beyond it
        d = float(model_braking_distance(v, a_max, integrator, GRAD_DT / n))
        rows += [(q_max - d, v), (q_min + d, -v), (q_max - 0.5 * d, v), (q_min + 0.5 * d, -v)]
    rows += [(q_max - 0.25 * GRAD_DT, 0.5), (q_min + 0.25 * GRAD_DT, -0.5)]  # Alg. 1's branch boundary 2 d = dt v
    q = np.array([r[0] for r in rows])
    v = np.array([r[1] for r in rows])
    a_prev = np.array([0.0, a_max, -a_max, 3.0, -7.0])[np.arange(len(q)) % 5]
    return q, v, a_prev


@pytest.mark.parametrize("integrator, substeps", GRAD_MODELS)
@pytest.mark.parametrize("method", ["naive", "viability", "jerk"])
def test_gradients_finite_on_exact_limits_without_rounding_guard(method, integrator, substeps, dtype):
    """The default guard moves the limits a few ulps inward, so no state sits on the limits the formulas use;
    without it these states do: ``jax.grad`` and ``jax.jacfwd`` w.r.t. q and v stay finite."""
    q, v, a_prev = (x.astype(dtype) for x in limit_states(integrator, substeps))
    lim = jl.JointLimits(*GRAD_LIM)
    extra = dict(a_prev=a_prev) if method == "jerk" else {}

    def both(q, v):
        b = jl.acc_bounds(
            q, v, lim, GRAD_DT, method=method, integrator=integrator, substeps=substeps, rounding_guard=False, **extra
        )
        return b.lower + b.upper

    @jax.jit
    def derivatives(q, v):  # one compilation for both modes
        return (
            both(q, v),
            jax.grad(lambda q, v: jnp.sum(both(q, v)), argnums=(0, 1))(q, v),
            jax.jacfwd(both, argnums=(0, 1))(q, v),
        )

    value, grads, jac = derivatives(q, v)
    assert np.all(np.isfinite(np.asarray(value)))
    for name, g in zip(("q", "v"), grads):
        assert np.all(np.isfinite(np.asarray(g))), (name, np.flatnonzero(~np.isfinite(np.asarray(g))), g)
    for name, j in zip(("q", "v"), jac):
        j = np.asarray(j)
        assert j.shape == (len(q), len(q))
        assert np.all(np.isfinite(j)), (name, np.argwhere(~np.isfinite(j)))
        # the bounds are elementwise: the Jacobian is diagonal (its diagonal is the gradient, except where a
        # state sits on a kink, e.g. exactly at the -a_max clip, which the two modes' roundings may resolve apart)
        np.testing.assert_array_equal(j - np.diag(np.diag(j)), 0.0)
    assert np.any(np.asarray(grads[0]) != 0) and np.any(np.asarray(grads[1]) != 0)  # not all clipped flat


# ----------------------------------------------------------------------------- 3. the conflict rule's values


def zoh_upper_ok(a, d, v, v_max, a_max, T):
    """Zero-order hold, upper side, by direct evaluation: ``|a| <= a_max``, ``q(t) <= q_max`` for ``t in (0, T]``
    (the parabola's end and its vertex if inside), ``v(T) <= v_max`` and the next state upper-viable."""
    a, d, v = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in (a, d, v)))
    ok = (np.abs(a) <= a_max) & (T * v + 0.5 * T * T * a <= d)
    neg = a < 0
    t = np.where(neg, -v / np.where(neg, a, -1.0), -1.0)
    inside = (t > 0) & (t < T)
    ok &= ~inside | (v * t + 0.5 * a * t * t <= d)
    v1, d1 = v + T * a, d - T * v - 0.5 * T * T * a
    return ok & (v1 <= v_max) & (np.maximum(v1, 0.0) ** 2 / (2.0 * a_max) <= d1)


def zoh_upper_bound(d, v, v_max, a_max, T, bisections=64):
    d, v = np.broadcast_arrays(np.asarray(d, np.float64), np.asarray(v, np.float64))
    good, bad = np.full(d.shape, -a_max), np.full(d.shape, a_max)
    top = zoh_upper_ok(bad, d, v, v_max, a_max, T)
    for _ in range(bisections):
        mid = 0.5 * (good + bad)
        passed = zoh_upper_ok(mid, d, v, v_max, a_max, T)
        good, bad = np.where(passed, mid, good), np.where(passed, bad, mid)
    return np.where(top, a_max, good)


def side_references(q, v, lim, dt, integrator, n):
    """Each side's own value by brute force (``-a_max``/``+a_max`` where nothing meets it): (lower, upper)."""
    q_min, q_max, v_max, a_max = lim
    if integrator == "zoh":
        upper = zoh_upper_bound(q_max - q, v, v_max, a_max, dt)
        lower = -zoh_upper_bound(q - q_min, -v, v_max, a_max, dt)
    else:
        upper = sir.upper_bound(q_max - q, v, v_max, a_max, dt, n)
        lower = -sir.upper_bound(q - q_min, -v, v_max, a_max, dt, n)
    return lower, upper


def far_out_states(lim, dt, count, rng):
    """States over the whole box the bounds treat without saturation: ``q`` one range past either limit,
    ``|v| <= 2 v_max + 4 a_max dt``, a quarter at rest."""
    q_min, q_max, v_max, a_max = lim
    span, v_sat = q_max - q_min, 2.0 * v_max + 4.0 * a_max * dt
    q = rng.uniform(q_min - span, q_max + span, count)
    v = rng.uniform(-v_sat, v_sat, count) * (rng.uniform(size=count) > 0.25)
    return q, v


@pytest.mark.parametrize("cfg", CONFIGS, ids=[_id(c) for c in CONFIGS])
def test_conflict_collapses_to_the_braking_action_of_the_side_moved_toward(cfg, x64):
    """``acc_bounds`` docstring: when the upper- and lower-side constraints conflict, the interval collapses to
    the braking action on the side the joint moves toward (at rest: the side of the midpoint it is on).

    Each side's value is computed independently (bisection on a step simulation followed by full braking):
    the largest ``a`` the upper-side limits allow (``-a_max`` if none), the smallest the lower-side ones allow.
    Conflict: lower > upper. Moving toward ``q_max`` the result is the upper side's value (the least braking
    that still meets ``q_max``'s constraints, full braking if none), toward ``q_min`` the lower side's.
    """
    lim, dt, integrator, n = cfg
    q_min, q_max, v_max, a_max = lim
    q, v = far_out_states(lim, dt, 6000, np.random.default_rng(3))
    ref_lower, ref_upper = side_references(q, v, lim, dt, integrator, n)
    tol = 1e-9 * a_max
    conflict = ref_lower > ref_upper + tol
    toward_upper = (v > 0) | ((v == 0) & (2 * q >= q_min + q_max))
    for method in ("viability", "naive"):
        b = jl.acc_bounds(
            q, v, jl.JointLimits(*lim), dt, method=method, integrator=integrator, substeps=n, rounding_guard=False
        )
        lower, upper = np.asarray(b.lower), np.asarray(b.upper)
        assert np.all(lower <= upper)
        assert not np.any(np.asarray(b.viable)[conflict])
        if method == "naive":  # only the order and the collapse: the naive sides are not the exact ones
            continue
        brake = np.where(toward_upper, ref_upper, ref_lower)
        np.testing.assert_allclose(lower[conflict], brake[conflict], rtol=0, atol=tol)
        np.testing.assert_allclose(upper[conflict], brake[conflict], rtol=0, atol=tol)
        # the chosen action slows the motion toward the side moved toward (never speeds it up)
        moving = conflict & (v != 0)
        assert np.all(np.where(v > 0, upper, -lower)[moving] <= np.where(v > 0, ref_lower, -ref_upper)[moving])
        # elsewhere the interval is exactly the two sides' values
        np.testing.assert_allclose(lower[~conflict], ref_lower[~conflict], rtol=0, atol=tol)
        np.testing.assert_allclose(upper[~conflict], ref_upper[~conflict], rtol=0, atol=tol)
    if dt < 0.05:  # a wide range with respect to a_max dt^2: conflicts are common, both ways
        assert np.count_nonzero(conflict & (v > 0)) > 100 and np.count_nonzero(conflict & (v < 0)) > 100


JERK_CONFIGS = [
    (JLimits1(-2.0, 2.0, 2.0, 12.0, 200.0), 0.01, "zoh", 1),
    (JLimits1(-0.5, 1.5, 2.5, 20.0, 500.0), 0.02, "semi_implicit", 4),
]


@pytest.mark.parametrize("cfg", JERK_CONFIGS, ids=["zoh-j200", "semi4-j500"])
def test_jerk_conflict_collapses_to_the_braking_action_of_the_side_moved_toward(cfg, x64):
    """The same rule in the jerk-aware bounds, against ``jerk_reference.position_threshold_dense`` (bisection on
    a step-by-step simulation of the max-braking plan inside the jerk box) for each side."""
    lim, dt, integrator, n = cfg
    rng = np.random.default_rng(5)
    q, v = far_out_states((lim.q_min, lim.q_max, lim.v_max, lim.a_max), dt, 600, rng)
    a_prev = lim.a_max * rng.uniform(-1, 1, len(q))
    ref_upper = position_threshold_dense(lim.q_max - q, v, a_prev, lim, dt, integrator, n)[0]
    ref_lower = -position_threshold_dense(q - lim.q_min, -v, -a_prev, lim, dt, integrator, n)[0]
    conflict = ref_lower > ref_upper + 1e-6 * lim.a_max
    assert np.count_nonzero(conflict & (v > 0)) > 20 and np.count_nonzero(conflict & (v < 0)) > 20
    b = jl.acc_bounds(
        q,
        v,
        jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max, j_max=lim.j_max),
        dt,
        method="jerk",
        integrator=integrator,
        substeps=n,
        rounding_guard=False,
        a_prev=a_prev,
    )
    lower, upper = np.asarray(b.lower), np.asarray(b.upper)
    toward_upper = (v > 0) | ((v == 0) & (2 * q >= lim.q_min + lim.q_max))
    brake = np.where(toward_upper, ref_upper, ref_lower)
    np.testing.assert_array_equal(lower[conflict], upper[conflict])
    # the library's threshold is lowered by a rounding margin and may fall back to the hardest braking
    np.testing.assert_allclose(upper[conflict], brake[conflict], rtol=0, atol=1e-6 * lim.a_max)


@pytest.mark.parametrize("method", ["naive", "viability", "jerk", "jerk_paper"])
def test_every_family_resolves_conflicts_by_the_documented_rule(method, x64):
    """``acc_bounds`` = ``bound_terms``' min/max clipped into the ``"acceleration"`` box, then, where the sides
    conflict, the side moved toward; at rest, the side of the midpoint the joint is on. The paper's jerk bounds
    (not exact) conflict at rest too, which is where the at-rest half of the rule decides."""
    lim = (-2.0, 2.0, 2.0, 12.0, 200.0)
    dt = 0.01
    q_min, q_max = lim[0], lim[1]
    rng = np.random.default_rng(11)
    q, v = far_out_states(lim[:4], dt, 3000, rng)
    q[:200] = np.where(np.arange(200) % 2 == 0, q_min - 1e-3, q_max + 1e-3)  # just outside, at rest or not
    extra = dict(a_prev=lim[3] * rng.uniform(-1, 1, len(q))) if method.startswith("jerk") else {}
    kw = dict(method=method, rounding_guard=False, **extra)
    limits = jl.JointLimits(*lim) if extra else jl.JointLimits(*lim[:4])
    b = jl.acc_bounds(q, v, limits, dt, **kw)
    t = jl.bound_terms(q, v, limits, dt, **kw)
    box_lo, box_hi = np.asarray(t["lower"]["acceleration"]), np.asarray(t["upper"]["acceleration"])
    upper = np.clip(np.min(np.stack([np.asarray(x) for x in t["upper"].values()]), 0), box_lo, box_hi)
    lower = np.clip(np.max(np.stack([np.asarray(x) for x in t["lower"].values()]), 0), box_lo, box_hi)
    conflict = lower > upper
    toward_upper = (v > 0) | ((v == 0) & (2 * q >= q_min + q_max))
    brake = np.where(toward_upper, upper, lower)
    tol = 1e-12 * lim[3]  # the jerk bounds are one fused XLA computation, their terms another: ulps apart
    np.testing.assert_allclose(np.asarray(b.lower), np.where(conflict, brake, lower), rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(b.upper), np.where(conflict, brake, upper), rtol=0, atol=tol)
    assert np.count_nonzero(conflict & (v > 0)) > 50 and np.count_nonzero(conflict & (v < 0)) > 50
    if method == "jerk_paper":
        assert np.count_nonzero(conflict & (v == 0) & toward_upper) > 20
        assert np.count_nonzero(conflict & (v == 0) & ~toward_upper) > 20


@pytest.mark.parametrize(
    "cfg",
    JERK_CONFIGS + [(JLimits1(-2.0, 2.0, 2.0, 12.0, 200.0), 0.01, "semi_implicit", 5)],
    ids=["zoh-j200", "semi4-j500", "semi5-j200"],
)
def test_jerk_viability_is_the_dense_max_braking_test(cfg, x64):
    """``is_viable_jerk`` against a step-by-step simulation of the hardest braking the jerk allows
    (``jerk_reference.braking_peak_dense``: every instant for zoh, every substep for semi-implicit) on states
    1e-9 of the peak on either side of it: viable iff both sides' max-braking plans stay inside."""
    lim, dt, integrator, n = cfg
    rng = np.random.default_rng(17)
    m = 400
    A, delta = lim.a_max, lim.j_max * dt
    v = lim.v_max * rng.uniform(0.05, 0.9, m)
    a_prev = A * rng.uniform(-1, 1, m)
    lo = np.maximum(a_prev - delta, -A)
    peak = braking_peak_dense(v, lo, lim, dt, integrator, n)
    d = peak * (1.0 + np.where(np.arange(m) % 2 == 0, 1e-9, -1e-9))
    # the plan's velocities: v_i = v + T sum_{j < i} max(lo - j delta, -A), i >= 1
    steps = np.arange(int(np.ceil(2 * A / delta)) + 2)[:, None]
    v_peak = v + dt * np.max(np.cumsum(np.maximum(lo - steps * delta, -A), axis=0), axis=0)
    expected = (d >= peak) & (v_peak <= lim.v_max)
    assert 0.3 * m < np.count_nonzero(expected) < 0.7 * m
    side = np.where(rng.uniform(size=m) < 0.5, 1.0, -1.0)
    q = np.where(side > 0, lim.q_max - d, lim.q_min + d)
    limits = jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max, j_max=lim.j_max)
    got = np.asarray(jl.is_viable_jerk(q, side * v, side * a_prev, limits, dt, integrator=integrator, substeps=n))
    np.testing.assert_array_equal(got, expected)
