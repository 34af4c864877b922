"""One contract over every registered limit family x discretisation (in the manner of optax's
``contrib/_common_test.py``): a family added to ``jl.METHODS`` is tested here without editing this file.

For each: jit = eager = vmap (to a few ulps of a_max: XLA folds the constant limits under jit); the input dtype kept; ``lower <= upper``; finite values
and gradients on the limits, on the family's own viability curve and past it; ``bound_terms`` is what
``acc_bounds`` takes the min/max of (clipped into the ``"acceleration"`` box, then the one conflict
rule); and the float32 rounding guard holds: riding the upper bound for a whole stop in float32,
simulated step by step, never leaves the position or velocity limits.
"""

from __future__ import annotations

import functools

import example_user_limit  # noqa: F401  (registers "half_speed", the user-written family of docs/architecture.md)
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlimits as jl

LIM = jl.JointLimits(
    q_min=[-1.0, -0.5, -2.0],
    q_max=[1.0, 0.5, 1.5],
    v_max=[2.0, 1.5, 2.5],
    a_max=[10.0, 8.0, 12.0],
    j_max=[600.0, 500.0, 800.0],
)
DT = 0.01
MODELS = [("zoh", 1), ("semi_implicit", 1), ("semi_implicit", 5)]
CASES = [(m, i, n) for m in sorted(jl.METHODS) for i, n in MODELS]
IDS = [f"{m}-{i}{n}" for m, i, n in CASES]


def call(method, integrator, substeps, q, v, a_prev, rounding_guard=True):
    limit = jl.make_limit(method, LIM, DT, integrator, substeps, rounding_guard)
    return limit.bounds(q, v, a_prev if limit.needs_a_prev else None)


def curve_speed(d, integrator, substeps):
    """The speed on this discretisation's viability curve at distance ``d`` (any shape ``(..., 3)``) from the
    upper limit (bisection; cached, the same distances recur over the parametrised tests)."""
    d = np.asarray(d, np.float64)
    return _curve_speed(d.tobytes(), d.shape, integrator, substeps).copy()


@functools.lru_cache(maxsize=None)
def _curve_speed(d_bytes, shape, integrator, substeps):
    d = np.frombuffer(d_bytes, np.float64).reshape(shape)
    lo, hi = np.zeros_like(d), np.full_like(d, 10.0)
    q = np.asarray(LIM.q_max) - d
    for _ in range(60):
        mid = (lo + hi) / 2
        with jax.enable_x64(True):
            ok = np.asarray(jl.is_viable(q, mid, LIM, integrator, DT, substeps)) | (mid > np.asarray(LIM.v_max))
            ok &= mid <= np.asarray(LIM.v_max)
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return lo


def states(integrator, substeps, dtype):
    """Random states inside, states on the limits, on the viability curve, on v_max, and past them."""
    rng = np.random.default_rng(7)
    q_min, q_max, v_max = (np.asarray(x) for x in (LIM.q_min, LIM.q_max, LIM.v_max))
    a_max = np.asarray(LIM.a_max)
    span = q_max - q_min
    q = [q_min + span * rng.uniform(0, 1, (24, 3))]
    v = [v_max * rng.uniform(-1, 1, (24, 3))]
    d = 0.2 * span
    vc = curve_speed(d, integrator, substeps)
    rows = [
        (q_max, 0 * q_max),
        (q_min, 0 * q_min),
        (q_max - d, vc),
        (q_min + d, -vc),
        (q_max, v_max),
        (q_min, -v_max),
        (q_max + 0.01, 0.5 * v_max),
        (q_min - 0.01, -v_max),
        (0 * q_max, 1.5 * v_max),
    ]
    q.append(np.stack([r[0] for r in rows]))
    v.append(np.stack([r[1] for r in rows]))
    q, v = np.concatenate(q), np.concatenate(v)
    a_prev = a_max * rng.uniform(-1, 1, q.shape)
    a_prev[-len(rows) :] = 0.0
    return q.astype(dtype), v.astype(dtype), a_prev.astype(dtype)


@pytest.mark.parametrize("method, integrator, substeps", CASES, ids=IDS)
def test_jit_eager_vmap_dtype_order_finite(method, integrator, substeps, dtype):
    q, v, a_prev = states(integrator, substeps, dtype)
    f = functools.partial(call, method, integrator, substeps)
    eager = f(q, v, a_prev)
    jitted = jax.jit(f)(q, v, a_prev)
    vmapped = jax.vmap(f)(q, v, a_prev)
    # Under jit the limits are constants that XLA folds at compile time (eagerly they are arguments): the
    # folded arithmetic may round differently, by a few ulps of a_max; viability flags are exact
    tol = 8 * np.finfo(dtype).eps * np.max(np.asarray(LIM.a_max))
    for a, b, c in zip(eager, jitted, vmapped):
        assert a.dtype == b.dtype == c.dtype
        if a.dtype == jnp.bool_:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
        else:
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=tol)
            np.testing.assert_allclose(np.asarray(a), np.asarray(c), rtol=0, atol=tol)
    assert eager.lower.dtype == jnp.dtype(dtype) and eager.viable.dtype == jnp.bool_
    lower, upper = np.asarray(eager.lower), np.asarray(eager.upper)
    assert np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))
    assert np.all(lower <= upper)
    a_max = np.asarray(LIM.a_max)
    assert np.all(lower >= -a_max * (1 + 1e-6)) and np.all(upper <= a_max * (1 + 1e-6))


@pytest.mark.parametrize("method, integrator, substeps", CASES, ids=IDS)
def test_gradients_finite_on_limits_and_curve(method, integrator, substeps, dtype):
    """(``rounding_guard=False``, where the states sit exactly on the formulas' limits: test_mutation_net.py)"""
    rounding_guard = True
    q, v, a_prev = states(integrator, substeps, dtype)

    def total(q, v, a_prev):
        b = call(method, integrator, substeps, q, v, a_prev, rounding_guard)
        return jnp.sum(b.lower + b.upper)

    grads = jax.grad(total, argnums=(0, 1, 2))(q, v, a_prev)
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g))), g
    # and one state at a time, moving outward from each limit (forward mode)
    for sign in (1.0, -1.0):
        tq = jnp.full_like(q, sign)
        _, jq = jax.jvp(lambda x: total(x, v, a_prev), (q,), (tq,))
        assert np.isfinite(float(jq))


@pytest.mark.parametrize("method, integrator, substeps", CASES, ids=IDS)
def test_bound_terms_are_what_acc_bounds_reduces(method, integrator, substeps, dtype):
    q, v, a_prev = states(integrator, substeps, dtype)
    limit = jl.make_limit(method, LIM, DT, integrator, substeps)
    ap = a_prev if limit.needs_a_prev else None
    kwargs = dict(method=method, integrator=integrator, substeps=substeps, a_prev=ap)
    terms = jl.bound_terms(q, v, LIM, DT, **kwargs)
    b = jl.acc_bounds(q, v, LIM, DT, **kwargs)
    assert set(terms) == {"upper", "lower"} and "acceleration" in terms["upper"] and "acceleration" in terms["lower"]
    box_lo, box_hi = terms["lower"]["acceleration"], terms["upper"]["acceleration"]
    up = jnp.clip(functools.reduce(jnp.minimum, terms["upper"].values()), box_lo, box_hi)
    lo = jnp.clip(functools.reduce(jnp.maximum, terms["lower"].values()), box_lo, box_hi)
    ok = np.asarray(lo <= up)
    tol = 8 * np.finfo(dtype).eps * np.max(np.asarray(LIM.a_max))  # compiled apart: XLA's fusions round apart
    np.testing.assert_allclose(np.asarray(b.lower)[ok], np.asarray(lo)[ok], rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(b.upper)[ok], np.asarray(up)[ok], rtol=0, atol=tol)
    # conflicts collapse to one end of the reduced interval (the braking side, tests/test_mutation_net.py)
    bad = ~ok
    assert np.all(np.asarray(b.lower)[bad] == np.asarray(b.upper)[bad])
    ends = np.minimum(np.abs(np.asarray(b.lower) - np.asarray(lo)), np.abs(np.asarray(b.lower) - np.asarray(up)))
    assert np.all(ends[bad] <= tol)
    assert terms["upper"]["acceleration"].dtype == jnp.dtype(dtype)


@pytest.mark.parametrize("method, integrator, substeps", CASES, ids=IDS)
def test_refused_by_both_or_accepted_by_both(method, integrator, substeps):
    q, v, a_prev = states(integrator, substeps, np.float32)
    limit = jl.make_limit(method, LIM, DT, integrator, substeps)
    wrong = None if limit.needs_a_prev else a_prev  # the state the family does not have
    for fn in (jl.acc_bounds, jl.bound_terms):
        with pytest.raises(ValueError, match="a_prev"):
            fn(q, v, LIM, DT, method=method, integrator=integrator, substeps=substeps, a_prev=wrong)
    for fn in (jl.acc_bounds, jl.bound_terms):
        with pytest.raises(ValueError, match="method must be one of"):
            fn(q, v, LIM, DT, method=method + "_typo", integrator=integrator, substeps=substeps)


def _ride_upper_bound(method, integrator, substeps, steps=120):
    """float32: start near the upper limit moving toward it, command the upper bound every step."""
    rng = np.random.default_rng(3)
    q_max = np.asarray(LIM.q_max)
    d = np.geomspace(1e-6, 0.3, 64)[:, None] * (q_max - np.asarray(LIM.q_min))
    vc = curve_speed(d, integrator, substeps)
    q = (q_max - d).astype(np.float32)
    v = (vc * rng.uniform(0.5, 1.0, vc.shape)).astype(np.float32)
    limit = jl.make_limit(method, LIM, DT, integrator, substeps)

    @jax.jit
    def rollout(q, v):
        def body(carry, _):
            q, v, a_prev, worst, worst_all = carry
            b = limit.bounds(q, v, a_prev if limit.needs_a_prev else None)
            viable = b.viable
            s = jl.integrate_step(q, v, b.upper, DT, integrator, substeps)
            q_max, v_max = (jnp.asarray(x, jnp.float32)[None] for x in (LIM.q_max, LIM.v_max))
            over = jnp.maximum(s.q_high - q_max, jnp.abs(s.v) - v_max)
            worst = jnp.where(viable, jnp.maximum(worst, over), worst)
            return (s.q, s.v, b.upper, worst, jnp.maximum(worst_all, over)), viable

        init = (q, v, jnp.zeros_like(q), jnp.full_like(q, -jnp.inf), jnp.full_like(q, -jnp.inf))
        (_, _, _, worst, worst_all), viable = jax.lax.scan(body, init, None, length=steps)
        return worst, worst_all, viable

    return rollout(q, v)


@pytest.mark.parametrize("method, integrator, substeps", CASES, ids=IDS)
def test_float32_guard_holds_riding_the_upper_bound(method, integrator, substeps):
    safe = jl.METHODS[method].guarantees_safety
    # a baseline only has to overshoot (jerk_paper does within 20 steps; its bounds run slowly at the suite's
    # optimisation level 0: 10 s for 120 steps, 3.5 s for 40)
    worst, worst_all, viable = _ride_upper_bound(method, integrator, substeps, steps=120 if safe else 40)
    if safe:
        # every step from a state the family calls viable stays inside, in float32, and its next state is
        # viable again (the induction the guarantee rests on); most of the ride is judged
        viable = np.asarray(viable)
        assert np.all(np.asarray(worst) <= 0.0), float(np.max(worst))
        assert not np.any(viable[:-1] & ~viable[1:]), "a viable state's successor left the kernel"
        assert np.mean(viable) > 0.9
    else:
        # a baseline (naive, jerk_paper) claims no safety, and riding its bound does overshoot
        assert np.any(np.asarray(worst_all) > 0.0)
