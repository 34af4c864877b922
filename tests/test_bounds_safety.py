"""Safety and exactness of the viability bounds, checked by simulating what happens next.

States are drawn near the limits and near the viability curve of each model (its own braking
distance: ``v^2 / (2 a_max)`` for zoh, the discrete ``D(v)`` for semi-implicit Euler); the step is
simulated by the independent NumPy simulators of ``reference.py`` (continuous time for zoh, every
substep for the semi-implicit model) and the next state's viability is decided by simulated full
braking. Seeds are fixed (``zlib.crc32`` of a name, not the per-process salted ``hash``).
"""

from __future__ import annotations

import math
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

import jaxlimits as jl
import semi_implicit_reference as sir
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


def braking_distance(v, lim: Limits1, T, integrator, n):
    """The model's own viability curve ``d = D(v)`` (independent of the library; semi-implicit summed term by term)."""
    if integrator == "zoh":
        return max(v, 0.0) ** 2 / (2.0 * lim.a_max)
    return float(sir.braking_distance(v, lim.a_max, T / n))


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
    elif mode == "near_curve":  # just inside the model's own curve, 1e-11 to 1e-3 of D(v) (or of 1e-9 rad) away
        v = lim.v_max * u
        base = braking_distance(v, lim, T, integrator, n)
        d = base + max(base, 1e-9) * 10.0 ** (-11.0 + 8.0 * w)
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
        b = jl.acc_bounds(
            jnp.float64(q),
            jnp.float64(v),
            jl_limits(lim),
            T,
            integrator=integrator,
            substeps=n,
            rounding_guard=rounding_guard,
        )
        return float(b.lower), float(b.upper), bool(b.viable)


def is_safe_step(q, v, a, name, tol=1e-12):
    """Whether a held ``a`` keeps every limit during the step and leaves a viable state."""
    lim, T, integrator, n = CONFIGS[name]
    q1, v1, q_lo, q_hi = simulate(q, v, a, T, integrator, n)
    return (
        abs(a) <= lim.a_max + tol
        and q_lo >= lim.q_min - tol
        and q_hi <= lim.q_max + tol
        and abs(v1) <= lim.v_max + tol
        and viable_reference(q1, v1, lim, integrator, T, n, tol=tol)
    )


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


def curve_state(name, v_frac, rel, kink, upper_side):
    """A state at relative distance ``rel`` inside the model's own viability curve, ``d = D(v) (1 + rel)``.

    ``kink``: for semi-implicit Euler, ``v`` is moved to the nearest kink of ``D``, ``v = K h a_max``.
    """
    lim, T, integrator, n = CONFIGS[name]
    v = lim.v_max * v_frac
    if kink and integrator == "semi_implicit":
        step = lim.a_max * T / n
        v = min(max(round(v / step), 1) * step, lim.v_max)
    d = braking_distance(v, lim, T, integrator, n) * (1.0 + rel)
    return (lim.q_max - d, v) if upper_side else (lim.q_min + d, -v)


def violates_under_full_braking(q, v, a, name):
    """Hold ``a`` for one step, then brake fully against the motion until it stops: does any limit break?

    Positions at every instant (zoh) or substep (semi-implicit), velocities at every step end, tolerance 0.
    """
    lim, T, integrator, n = CONFIGS[name]
    sign = 1.0 if v + T * a >= 0 else -1.0  # the direction of the motion after the step
    for step in range(int(math.ceil(2.0 * (lim.v_max + lim.a_max * T) / (lim.a_max * T))) + 3):
        q, v, q_lo, q_hi = (float(x) for x in simulate(q, v, a, T, integrator, n))
        if q_hi > lim.q_max or q_lo < lim.q_min or abs(v) > lim.v_max:
            return True
        if sign * v <= 0:
            return False
        a = -sign * lim.a_max
    raise AssertionError("full braking did not stop")


CURVE_EXAMPLES = [
    dict(name=name, v_frac=v_frac, rel=0.0, kink=kink, upper_side=side)
    for name in ("fig4-zoh", "fig4-semi5", "edge11-semi7", "slow-semi5")
    for v_frac, kink in ((1.0, False), (0.37, False), (0.37, True))
    for side in (True, False)
]


def _with_examples(test):
    for kwargs in CURVE_EXAMPLES:
        test = example(**kwargs)(test)
    return test


@settings(max_examples=60)
@given(
    name=st.sampled_from(sorted(CONFIGS)),
    v_frac=st.floats(0.0, 1.0),
    rel=st.one_of(st.just(0.0), st.floats(-15.0, -3.0).map(lambda x: 10.0**x)),
    kink=st.booleans(),
    upper_side=st.booleans(),
)
@_with_examples
def test_states_on_each_models_own_curve_are_safe_and_tight(name, v_frac, rel, kink, upper_side):
    """On (``rel = 0``, the ``@example``s) and just inside the viability curve of the model the bounds are for:

    * safe: every end of the interval and its midpoint keeps the limits during the step (continuous time
      or every substep), and so does riding the upper end for three more steps (the next states viable);
    * tight: the exact (unguarded) bound plus 1e-6 a_max (more at tiny speeds), then full braking, breaks a limit.
    """
    lim, T, integrator, n = CONFIGS[name]
    q, v = curve_state(name, v_frac, rel, kink, upper_side)
    assert viable_reference(q, v, lim, integrator, T, n, tol=1e-12)
    lower, upper, viable = bounds64(name, q, v)
    # only a state within rounding of the curve may read as outside it (tiny v: D(v) below an ulp of q)
    gap = (lim.q_max - q if upper_side else q - lim.q_min) - braking_distance(abs(v), lim, T, integrator, n)
    assert viable or gap <= 8 * np.spacing(max(abs(lim.q_min), abs(lim.q_max))), (gap, q, v)
    for a in (lower, upper, 0.5 * (lower + upper)):
        assert is_safe_step(q, v, a, name), (name, q, v, a, lower, upper)
    qk, vk = q, v
    for _ in range(3):
        lo_k, up_k, _ = bounds64(name, qk, vk)
        a = up_k if upper_side else lo_k
        assert is_safe_step(qk, vk, a, name), (name, qk, vk, a)
        qk, vk = (float(x) for x in simulate(qk, vk, a, T, integrator, n)[:2])
    # 1e-6 a_max, or more where the overshoot it causes (>= v^2 eps / (2 a_max^2) when the stop comes inside
    # the step) would be below the float64 resolution of the position
    eps = max(1e-6 * lim.a_max, 1e-11 * lim.a_max**2 / max(v * v, 1e-300))
    lower, upper, _ = bounds64(name, q, v, rounding_guard=False)
    if upper < lim.a_max - eps and eps <= 1e-2 * lim.a_max:
        assert violates_under_full_braking(q, v, upper + eps, name), (name, q, v, upper)
    if lower > -lim.a_max + eps and eps <= 1e-2 * lim.a_max:
        assert violates_under_full_braking(q, v, lower - eps, name), (name, q, v, lower)
    # on the zoh curve, moving toward the limit, only full braking is left on that side (the semi-implicit D is
    # flat below v = h a_max and piecewise linear: less braking can still stop in time there)
    # (not where v^2 underflows: then the curve is q on the limit itself and any a ~ -v/T keeps it, to rounding)
    if rel == 0.0 and v * v > 1e-300 and integrator == "zoh":
        assert (upper if upper_side else -lower) <= -lim.a_max + 1e-9 * lim.a_max, (upper, lower)


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
    rng = np.random.default_rng(zlib.crc32(f"{name}/{policy}".encode()))
    q, v = (x.astype(dtype) for x in initial_states(lim, integrator, T, n, count, rng))
    switch = rng.integers(1, 20, size=count)
    limits = jl_limits(lim)
    with jax.enable_x64(dtype == np.float64):
        fn = jax.jit(
            lambda q, v: jl.acc_bounds(
                q, v, limits, T, method=method, integrator=b_integrator, substeps=b_sub, rounding_guard=rounding_guard
            )
        )
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
