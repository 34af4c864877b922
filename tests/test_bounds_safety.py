"""Safety and exactness of the viability bounds, checked by simulating what happens next.

States are drawn near the limits and near the viability curve; the step is simulated by the
independent NumPy simulators of ``reference.py`` (continuous time for zoh, every substep for the
semi-implicit model) and the next state's viability is decided by simulated full braking.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

import jaxlimits as jl
from reference import Limits1, semi_implicit_step, viable_reference, zoh_step, zoh_step_dtype

CONFIGS = {
    "fig3-zoh": (Limits1(-0.5, 0.5, 2.0, 10.0), 0.1, "zoh", 1),
    "fig4-zoh": (Limits1(-2.0, 2.0, 2.0, 12.0), 0.01, "zoh", 1),
    # condition (11) within 0.02 % of equality (it must hold with 0.01 % to spare)
    "edge11-zoh": (Limits1(-0.05, 0.05, 1.0, 10.0 * (1 - 2e-4)), 0.1, "zoh", 1),
    "fig4-semi1": (Limits1(-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 1),
    "fig4-semi5": (Limits1(-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 5),
    "fig3-semi4": (Limits1(-0.5, 0.5, 2.0, 10.0), 0.1, "semi_implicit", 4),
    "edge11-semi7": (Limits1(-0.05, 0.05, 1.0, 10.0 * (1 - 2e-4)), 0.1, "semi_implicit", 7),
    "asym-semi10": (Limits1(-0.3, 1.7, 1.5, 20.0), 0.02, "semi_implicit", 10),
    # long stops (v_max / a_max = 0.8 s, a Panda joint at a fraction of its datasheet a_max): the
    # roundings of a whole stop add up, which a one-step rounding margin did not cover
    "slow-zoh": (Limits1(-2.8973, 2.8973, 2.175, 2.7), 0.01, "zoh", 1),
    "slow-semi5": (Limits1(-2.8973, 2.8973, 2.175, 2.7), 0.01, "semi_implicit", 5),
}


def jl_limits(lim: Limits1) -> jl.JointLimits:
    return jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max)


def simulate(q, v, a, T, integrator, n, dtype=np.float64):
    """(q1, v1, q_lo, q_hi) by the reference simulator, the end state rounded to ``dtype``."""
    if integrator == "zoh":
        return zoh_step_dtype(q, v, a, T, dtype) if dtype != np.float64 else zoh_step(q, v, a, T)
    return semi_implicit_step(q, v, a, T, n, dtype)


@st.composite
def near_limit_states(draw):
    """(config name, q, v): viable states concentrated near a limit and near the viability curve."""
    name = draw(st.sampled_from(sorted(CONFIGS)))
    lim, T, integrator, n = CONFIGS[name]
    span = lim.q_max - lim.q_min
    mode = draw(st.sampled_from(["at_limit", "near_limit", "near_curve", "anywhere"]))
    u = draw(st.floats(0.0, 1.0))
    w = draw(st.floats(0.0, 1.0))
    if mode == "at_limit":
        d = span * u**8 if u < 0.9 else 0.0
        v = -lim.v_max * w if w < 0.8 else 0.0
    elif mode == "near_limit":
        d = span * u**4
        v = math.sqrt(2 * lim.a_max * d) * (2 * w - 1)
    elif mode == "near_curve":
        d = span * u
        v = min(lim.v_max, math.sqrt(2 * lim.a_max * d)) * (1.0 + 0.05 * (w - 0.75) * w**3)
    else:
        d = span * u
        v = lim.v_max * (2 * w - 1)
    v = min(v, lim.v_max)
    if draw(st.booleans()):
        q = lim.q_max - d
    else:
        q, v = lim.q_min + d, -v
    assume(viable_reference(q, v, lim, integrator, T, n, curve_margin=1e-12))
    return name, q, v


def bounds64(name, q, v, rounding_guard=True):
    lim, T, integrator, n = CONFIGS[name]
    with jax.enable_x64(True):
        b = jl.acc_bounds(jnp.float64(q), jnp.float64(v), jl_limits(lim), T, integrator=integrator,
                          substeps=n, rounding_guard=rounding_guard)
        return float(b.lower), float(b.upper), bool(b.viable)


def is_safe_step(q, v, a, name, tol=1e-12):
    """Whether a held ``a`` keeps every limit during the step and leaves a viable state."""
    lim, T, integrator, n = CONFIGS[name]
    q1, v1, q_lo, q_hi = simulate(q, v, a, T, integrator, n)
    return (abs(a) <= lim.a_max + tol and q_lo >= lim.q_min - tol and q_hi <= lim.q_max + tol
            and abs(v1) <= lim.v_max + tol and viable_reference(q1, v1, lim, integrator, T, n, tol=tol))


@given(near_limit_states(), st.floats(0.0, 1.0))
def test_every_action_in_the_interval_is_safe(state, u):
    name, q, v = state
    lower, upper, viable = bounds64(name, q, v)
    assert viable
    assert lower <= upper
    for a in (lower, upper, 0.5 * (lower + upper), lower + u * (upper - lower)):
        assert is_safe_step(q, v, a, name), (name, q, v, a, lower, upper)


@given(near_limit_states())
def test_no_action_outside_the_interval_is_safe(state):
    """Exactness: just past either end, some limit breaks now or the next state is not viable."""
    name, q, v = state
    lim = CONFIGS[name][0]
    lower, upper, _ = bounds64(name, q, v, rounding_guard=False)
    delta = 1e-6 * lim.a_max
    if upper < lim.a_max - delta:
        assert not is_safe_step(q, v, upper + delta, name, tol=0.0), (name, q, v, upper)
    if lower > -lim.a_max + delta:
        assert not is_safe_step(q, v, lower - delta, name, tol=0.0), (name, q, v, lower)


def initial_states(lim: Limits1, integrator, T, n, count, rng):
    """Random viable states, half of them close to a limit, for rollouts."""
    qs, vs = [], []
    while len(qs) < count:
        d = (lim.q_max - lim.q_min) * rng.uniform() ** 2
        v = rng.uniform(-1, 1) * min(lim.v_max, math.sqrt(2 * lim.a_max * d))
        q, v = (lim.q_max - d, v) if rng.uniform() < 0.5 else (lim.q_min + d, -v)
        if viable_reference(q, v, lim, integrator, T, n):
            qs.append(q)
            vs.append(v)
    return np.array(qs), np.array(vs)


def policy_action(policy, step, lower, upper, switch, rng):
    if policy == "upper":
        return upper
    if policy == "lower":
        return lower
    if policy == "bang_bang":
        return np.where((step // switch) % 2 == 0, upper, lower)
    return lower + rng.uniform(size=lower.shape) * (upper - lower)


def rollout(name, policy, dtype, method="viability", steps=1500, count=32, bounds_integrator=None, rounding_guard=True):
    """Run ``count`` joints under ``policy`` for ``steps`` control steps; return the worst excursions."""
    lim, T, integrator, n = CONFIGS[name]
    b_integrator = bounds_integrator or integrator
    b_sub = n if b_integrator == "semi_implicit" else 1
    rng = np.random.default_rng(abs(hash((name, policy))) % 2**32)
    q, v = (x.astype(dtype) for x in initial_states(lim, integrator, T, n, count, rng))
    switch = rng.integers(1, 20, size=count)
    limits = jl_limits(lim)
    with jax.enable_x64(dtype == np.float64):
        fn = jax.jit(lambda q, v: jl.acc_bounds(q, v, limits, T, method=method, integrator=b_integrator,
                                                substeps=b_sub, rounding_guard=rounding_guard))
        worst = dict(position=0.0, velocity=0.0, acceleration=0.0, nonviable_steps=0)
        for k in range(steps):
            b = fn(q, v)
            lower, upper = np.asarray(b.lower), np.asarray(b.upper)
            worst["nonviable_steps"] += int(np.sum(~np.asarray(b.viable)))
            a = policy_action(policy, k, lower, upper, switch, rng).astype(dtype)
            q, v, q_lo, q_hi = simulate(q, v, a, T, integrator, n, dtype)
            worst["position"] = max(worst["position"], float(np.max(q_hi - lim.q_max)), float(np.max(lim.q_min - q_lo)))
            worst["velocity"] = max(worst["velocity"], float(np.max(np.abs(v.astype(np.float64)) - lim.v_max)))
            # against a_max as this dtype represents it (float32(9.998) > 9.998 by 1.4e-7)
            worst["acceleration"] = max(worst["acceleration"], float(np.max(np.abs(a) - dtype(lim.a_max))))
    return worst


@pytest.mark.parametrize("policy", ["upper", "lower", "bang_bang", "random"])
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_adversarial_rollouts_never_violate(name, policy, dtype):
    worst = rollout(name, policy, dtype)
    # float32: the default rounding guard keeps even a state riding a bound inside; the issue's
    # budget is 1e-6 rad of overshoot, float64 gets (almost) none.
    tol = 1e-6 if dtype == np.float32 else 1e-12
    assert worst["position"] <= tol, worst
    assert worst["velocity"] <= tol * CONFIGS[name][0].v_max, worst
    assert worst["acceleration"] <= 0.0, worst
    assert worst["nonviable_steps"] == 0, worst


@pytest.mark.parametrize("name", ["fig4-zoh", "fig3-semi4"])
def test_naive_bounds_violate_the_same_checks(name):
    """The checks above can fail: the one-step bounds (eq. 2) break the position limit."""
    worst = rollout(name, "upper", np.float64, method="naive", steps=300)
    assert worst["position"] > 1e-3, worst


@pytest.mark.parametrize("name", ["fig4-semi5", "asym-semi10"])
def test_zoh_bounds_are_unsafe_in_a_semi_implicit_simulator(name):
    """Why ``integrator`` exists: the paper's bounds under MuJoCo's update overshoot the limit."""
    worst = rollout(name, "upper", np.float64, bounds_integrator="zoh", steps=600)
    assert worst["position"] > 1e-6, worst


@pytest.mark.parametrize("name", ["fig4-zoh", "fig4-semi5", "asym-semi10"])
def test_float32_rounding_guard_is_what_keeps_states_viable(name):
    """Without the guard, exact bounds rounded in float32 stay within 1e-6 rad (stable formulas)
    but keep leaving the viable set by rounding; with it (the default) they never do."""
    bare = rollout(name, "upper", np.float32, steps=600, rounding_guard=False)
    guarded = rollout(name, "upper", np.float32, steps=600)
    assert bare["position"] <= 1e-6, bare
    assert bare["nonviable_steps"] > 0, bare
    assert guarded["position"] <= 0.0 and guarded["nonviable_steps"] == 0, guarded


@pytest.mark.parametrize("name", ["slow-zoh", "slow-semi5"])
def test_float32_guard_covers_the_roundings_of_a_whole_stop(name):
    """Riding the viability curve means braking at ``a_max`` until the stop, with nothing to correct
    the rounding on the way: over a 0.8 s stop the unguarded float32 rollout leaves the viable set
    thousands of times and overshoots by several um; the default guard (sized for a whole stop)
    keeps it inside."""
    bare = rollout(name, "upper", np.float32, steps=600, rounding_guard=False)
    guarded = rollout(name, "upper", np.float32, steps=600)
    assert bare["nonviable_steps"] > 0, bare
    assert guarded["position"] <= 0.0 and guarded["nonviable_steps"] == 0, guarded
