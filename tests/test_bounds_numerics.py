"""Behaviour on every input: shapes, dtypes, jit/vmap/eager, gradients, boundaries, extremes."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxlimits as jl
from conftest import count_compilations

LIM = jl.JointLimits(
    q_min=[-2.0, -0.5, -1.0, -2.9],
    q_max=[2.0, 0.5, 1.5, 2.9],
    v_max=[2.0, 2.0, 1.0, 2.6],
    a_max=[12.0, 10.0, 8.0, 15.0],
)
DT = 0.01
MODELS = [("zoh", 1), ("semi_implicit", 1), ("semi_implicit", 5)]
METHODS = ["viability", "naive"]


def random_states(rng, shape, spread=1.0):
    q_min, q_max = np.asarray(LIM.q_min), np.asarray(LIM.q_max)
    mid, half = (q_min + q_max) / 2, (q_max - q_min) / 2
    q = mid + half * rng.uniform(-spread, spread, size=shape)
    v = np.asarray(LIM.v_max) * rng.uniform(-spread, spread, size=shape)
    return q, v


def boundary_states():
    """States exactly on limits, on the viability curve and on the velocity limit, per joint."""
    q_min, q_max = np.asarray(LIM.q_min), np.asarray(LIM.q_max)
    v_max, a_max = np.asarray(LIM.v_max), np.asarray(LIM.a_max)
    d = 0.3 * (q_max - q_min)
    v_curve = np.minimum(np.sqrt(2 * a_max * d), v_max)
    rows = [
        (q_max, 0 * q_max),
        (q_min, 0 * q_min),  # on a limit, at rest
        (q_max - d, v_curve),
        (q_min + d, -v_curve),  # on the viability curve
        ((q_min + q_max) / 2, v_max),
        ((q_min + q_max) / 2, -v_max),  # on the velocity limit
        (q_max, -v_max),
        (q_min, v_max),  # on a limit, leaving fast
    ]
    return np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows])


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("integrator, substeps", MODELS)
def test_jit_eager_vmap_agree_and_keep_dtype(method, integrator, substeps, dtype):
    q, v = (x.astype(dtype) for x in random_states(np.random.default_rng(0), (16, 4)))
    f = lambda q, v: jl.acc_bounds(q, v, LIM, DT, method=method, integrator=integrator, substeps=substeps)  # noqa: E731
    eager = f(q, v)
    jitted = jax.jit(f)(q, v)
    vmapped = jax.vmap(f)(q, v)
    for a, b, c in zip(eager, jitted, vmapped):
        assert a.dtype == b.dtype == c.dtype
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    assert eager.lower.dtype == jnp.dtype(dtype)
    assert eager.viable.dtype == jnp.bool_


@pytest.mark.parametrize("shape", [(4,), (3, 4), (2, 3, 4), (1, 1, 4)])
def test_leading_batch_dimensions_and_broadcasting(shape):
    q, v = random_states(np.random.default_rng(1), shape)
    b = jl.acc_bounds(q, v, LIM, DT)
    assert b.lower.shape == b.upper.shape == b.viable.shape == shape
    flat = jl.acc_bounds(q.reshape(-1, 4), v.reshape(-1, 4), LIM, DT)
    np.testing.assert_array_equal(np.asarray(b.upper).reshape(-1, 4), np.asarray(flat.upper))
    # v broadcast against a batch of q
    one_v = jl.acc_bounds(q, v.reshape(-1, 4)[0], LIM, DT)
    assert one_v.upper.shape == shape
    # scalar limits apply to every joint
    scalar = jl.JointLimits(-2.0, 2.0, 2.0, 12.0)
    assert jl.acc_bounds(q, v, scalar, DT).upper.shape == shape


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("integrator, substeps", MODELS)
def test_float32_agrees_with_float64(method, integrator, substeps):
    q, v = random_states(np.random.default_rng(2), (256, 4))
    # the formulas agree without the rounding guard (which moves float32 limits by tens of um, see
    # ``_rounding_guard``); with it, float32 bounds are only ever tighter
    kw = dict(method=method, integrator=integrator, substeps=substeps, rounding_guard=False)
    b32 = jl.acc_bounds(q.astype(np.float32), v.astype(np.float32), LIM, DT, **kw)
    guarded = jl.acc_bounds(q.astype(np.float32), v.astype(np.float32), LIM, DT, **dict(kw, rounding_guard=True))
    inside = np.asarray(b32.viable)
    assert np.all(np.asarray(guarded.upper)[inside] <= np.asarray(b32.upper)[inside])
    assert np.all(np.asarray(guarded.lower)[inside] >= np.asarray(b32.lower)[inside])
    with jax.enable_x64(True):
        b64 = jl.acc_bounds(q, v, LIM, DT, **kw)
        scale = np.asarray(LIM.a_max)
        # float32 rounding of q near 2 rad is ~1e-7; the bound moves by up to 2/dt^2 per rad
        np.testing.assert_allclose(np.asarray(b32.upper), np.asarray(b64.upper), atol=2e-3 * scale.max())
        np.testing.assert_allclose(np.asarray(b32.lower), np.asarray(b64.lower), atol=2e-3 * scale.max())
        assert np.mean(np.asarray(b32.viable) == np.asarray(b64.viable)) > 0.99


@pytest.mark.parametrize("integrator, substeps", MODELS)
def test_interval_is_ordered_finite_and_inside_acceleration_limits_for_any_finite_input(integrator, substeps, dtype):
    rng = np.random.default_rng(3)
    q, v = random_states(rng, (4096, 4), spread=3.0)  # mostly far outside the limits
    big = np.finfo(dtype).max / 16
    extremes = np.array([0.0, 1e-30, -1e-30, 1e30, -1e30, big, -big], dtype=np.float64)
    combos = np.array(list(itertools.product(extremes, extremes)))
    q = np.concatenate([q, np.repeat(combos[:, :1], 4, axis=1)]).astype(dtype)
    v = np.concatenate([v, np.repeat(combos[:, 1:], 4, axis=1)]).astype(dtype)
    for method in METHODS:
        b = jl.acc_bounds(q, v, LIM, DT, method=method, integrator=integrator, substeps=substeps)
        lo, up = np.asarray(b.lower), np.asarray(b.upper)
        a_max = np.asarray(LIM.a_max, dtype)
        assert np.all(np.isfinite(lo)) and np.all(np.isfinite(up))
        assert np.all(lo <= up)
        assert np.all(lo >= -a_max) and np.all(up <= a_max)


def test_non_viable_states_get_the_braking_action():
    lim = jl.JointLimits(-2.0, 2.0, 2.0, 12.0)
    # too fast toward q_max to stop, past q_max moving out, past the velocity limit
    q = jnp.array([1.9, 2.01, 0.0, -1.9, -2.01])
    v = jnp.array([2.0, 0.5, 2.5, -2.0, -0.5])
    b = jl.acc_bounds(q, v, lim, DT)
    assert not np.any(np.asarray(b.viable))
    np.testing.assert_array_equal(np.asarray(b.upper[:3]), -12.0)
    np.testing.assert_array_equal(np.asarray(b.lower[:3]), -12.0)
    np.testing.assert_array_equal(np.asarray(b.lower[3:]), 12.0)
    # at rest just past q_max: accelerations that are back inside at the end of the step
    with jax.enable_x64(True):
        r = jl.acc_bounds(jnp.array([2.0 + 1e-4]), jnp.array([0.0]), lim, DT, rounding_guard=False)
        assert not bool(r.viable[0])
        end = 2.0 + 1e-4 + 0.5 * DT**2 * float(r.upper[0])
        assert end <= 2.0 + 1e-12 and float(r.lower[0]) <= float(r.upper[0])


@pytest.mark.parametrize("integrator, substeps", MODELS)
def test_is_viable_matches_the_bounds_flag(integrator, substeps):
    q, v = random_states(np.random.default_rng(4), (512, 4), spread=1.2)
    b = jl.acc_bounds(q, v, LIM, DT, integrator=integrator, substeps=substeps)
    flag = jl.is_viable(q, v, LIM, integrator=integrator, dt=DT, substeps=substeps)
    np.testing.assert_array_equal(np.asarray(flag), np.asarray(b.viable))
    assert 0.2 < np.mean(np.asarray(flag)) < 0.95


@pytest.mark.parametrize("integrator, substeps", MODELS)
@pytest.mark.parametrize("side", ["upper", "lower"])
def test_gradients_match_finite_differences_away_from_kinks(integrator, substeps, side, x64):
    q, v = random_states(np.random.default_rng(5), (400, 4), spread=0.98)
    # keep states that are viable and 1e-3 rad/s^2 away from a switch between constraint families
    terms = jl.bound_terms(q, v, LIM, DT, integrator=integrator, substeps=substeps)[side]
    vals = np.sort(np.stack([np.asarray(t) for t in terms.values()]), axis=0)
    gaps = (vals[1] - vals[0]) if side == "upper" else (vals[-1] - vals[-2])
    keep = np.all(gaps > 1e-3, axis=-1) & np.all(np.asarray(jl.is_viable(q, v, LIM, integrator, DT, substeps)), axis=-1)
    assert keep.sum() >= 20, keep.sum()
    q, v = jnp.asarray(q[keep]), jnp.asarray(v[keep])

    @jax.jit
    def f(q, v):
        return getattr(
            jl.acc_bounds(q, v, LIM, DT, integrator=integrator, substeps=substeps, rounding_guard=False), side
        )

    # eps small enough to stay inside one linear piece of the semi-implicit braking distance
    check_grads(f, (q, v), order=1, modes=("fwd", "rev"), eps=1e-7)

    # and with respect to a limit (a traced JointLimits field)
    @jax.jit
    def g(a_max):
        lim = jl.JointLimits(LIM.q_min, LIM.q_max, LIM.v_max, a_max)
        return getattr(
            jl.acc_bounds(q, v, lim, DT, integrator=integrator, substeps=substeps, rounding_guard=False), side
        )

    check_grads(g, (jnp.asarray(LIM.a_max),), order=1, modes=("fwd", "rev"), eps=1e-7)


@pytest.mark.parametrize("integrator, substeps", MODELS)
@pytest.mark.parametrize("method", METHODS)
def test_gradients_are_finite_exactly_on_boundaries(integrator, substeps, method, dtype):
    q, v = (x.astype(dtype) for x in boundary_states())

    def total(q, v, a_max):
        lim = jl.JointLimits(LIM.q_min, LIM.q_max, LIM.v_max, a_max)
        b = jl.acc_bounds(q, v, lim, DT, method=method, integrator=integrator, substeps=substeps)
        return jnp.sum(b.lower) + jnp.sum(b.upper)

    a_max = jnp.asarray(np.asarray(LIM.a_max), dtype)
    grads = jax.grad(total, argnums=(0, 1, 2))(q, v, a_max)
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))
    fwd = jax.jvp(lambda q: total(q, v, a_max), (q,), (jnp.ones_like(q),))[1]
    assert np.isfinite(float(fwd))


def test_jitted_step_does_not_recompile():
    f = jax.jit(lambda q, v: jl.acc_bounds(q, v, LIM, DT, integrator="semi_implicit", substeps=5))
    q, v = random_states(np.random.default_rng(6), (8, 4))
    q, v = q.astype(np.float32), v.astype(np.float32)
    f(q, v)
    with count_compilations() as compiled:
        for k in range(3):
            jax.block_until_ready(f(q + 0.01 * k, v))
    assert compiled == []
