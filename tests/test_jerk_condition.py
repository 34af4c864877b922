"""The jerk condition (``jerk_condition.py``): exact where it accepts, refused (and really failing) just below.

(a) At the issue's example (q in [-0.5, 0.5], v_max 2, a_max 10, j_max 60, dt 0.1 s: the old
condition asked for a 6.2 rad range) and at the new condition's edge (range and v_max at the needed
values, both integrators), the condition accepts, and the bounds are the long-horizon LP's exact
bounds on random viable states (``jerk_reference.lp_jerk_bounds_exact_first``) and on the states where the
decoupling is tightest (just under ``q_max``, nearly at rest, ``a_prev`` near ``-a_max``).
(b) Just below the needed range or v_max the condition raises a ``ValueError`` naming the joint,
the field, the value and the needed value, and there the per-side tests do fail: a state they call
viable is infeasible for the LP relaxation (which proves it is not viable).

Until ``jerk.py`` calls ``jerk_condition.check_jerk_condition`` itself, the bounds are computed with
``jl.acc_bounds(method="jerk")`` and the condition of ``jerk.py`` monkeypatched (``use_condition``):
to the new one where the tests claim exactness, to nothing where they show the failure below it.
A larger run: ``JERK_CONDITION_STATES=100 .venv/bin/python tests/test_jerk_condition.py`` (~10 min).
"""

from __future__ import annotations

import contextlib
import os
import sys
import zlib

import jax
import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

import jaxlimits as jl  # noqa: E402
from jaxlimits._src import jerk, jerk_condition  # noqa: E402
from jerk_reference import (  # noqa: E402
    JLimits1,
    braking_peak_dense,
    lp_jerk_bounds_exact_first,
    lp_jerk_feasible,
    sample_states,
    simulate_step,
)

CHECK = jerk_condition.check_jerk_condition  # the new condition, kept before any monkeypatch
EXAMPLE = JLimits1(-0.5, 0.5, 2.0, 10.0, 60.0)
EXAMPLE_DT = 0.1
LP_TOL = 1e-9  # rad/s^2: a bound above the LP's relaxed optimum, or below its restricted one, by more fails
ZOH_RESOLUTION = 3e-6  # rad: zoh LP rows per step s such that its bracket a_max (dt / s)^2 / 8 is this small


def zoh_samples(lim, T):
    return max(8, int(np.ceil(T * np.sqrt(lim.a_max / (8 * ZOH_RESOLUTION)))))


def jl_limits(lim: JLimits1) -> jl.JointLimits:
    return jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max, j_max=lim.j_max)


@contextlib.contextmanager
def use_condition(condition):
    """``jerk.py``'s condition replaced by ``condition`` (and ``jerk_condition``'s, if ``jerk.py`` calls it there).

    Temporary (see the module docstring): ``jerk.Jerk`` calls ``check_jerk_condition(limits, dt)``
    without the discretisation, so the wrapper passed here supplies it.
    """
    mp = pytest.MonkeyPatch()
    try:
        mp.setattr(jerk, "check_jerk_condition", condition, raising=False)
        mp.setattr(jerk_condition, "check_jerk_condition", condition)
        yield
    finally:
        mp.undo()


def bounds64(lim, T, integrator, n, q, v, a_prev, condition):
    """``acc_bounds(method="jerk")`` in float64 without the rounding guard, under ``condition``."""
    q, v, a_prev = (np.asarray(x, np.float64) for x in (q, v, a_prev))
    with use_condition(condition), jax.enable_x64(True):
        b = jl.acc_bounds(
            q,
            v,
            jl_limits(lim),
            T,
            method="jerk",
            integrator=integrator,
            substeps=n,
            rounding_guard=False,
            a_prev=a_prev,
        )
        return tuple(np.asarray(x) for x in b)


def new_condition(integrator, n):
    return lambda limits, dt, *args, **kwargs: CHECK(limits, dt, integrator, n)


def no_condition(*args, **kwargs):
    return None


def edge_limits(A, J, T, integrator, n, v_max=None, scale=1.0, v_scale=1.0):
    """Symmetric limits with range ``scale`` x and ``v_max`` ``v_scale`` x the needed values (``v_max``: given)."""
    span, vm = 1.0, 2.0 if v_max is None else v_max
    for _ in range(4):  # the rounding margin depends (weakly) on the limits themselves: a fixed point
        lim = JLimits1(-span / 2, span / 2, vm, A, J)
        need_span, need_v, _ = jerk_condition.jerk_condition_needs(jl_limits(lim), T, integrator, n)
        span = float(need_span) * scale
        vm = float(need_v) * v_scale if v_max is None else v_max
    return JLimits1(-span / 2, span / 2, vm, A, J)


def tight_states(lim, T, integrator, n, count, rng):
    """Where the decoupling is tightest: just under ``q_max`` (over ``q_min``, mirrored), nearly at rest, braking hard.

    ``v`` just above the worst peak's (0 zoh, ``h a_max`` semi-implicit), ``a_prev`` in
    ``[-a_max, -a_max + j_max dt]``, ``q`` with the max-braking plan of ``a_prev - delta`` peaking at or
    a little under ``q_max``.
    """
    A, delta, h = lim.a_max, lim.j_max * T, T / n
    a_w = A if integrator == "zoh" else min(A, lim.v_max / h)  # the worst peak's acceleration
    v0 = 0.0 if integrator == "zoh" else h * a_w
    v = np.minimum(v0 + A * T * rng.uniform(0, 1, count) ** 3 * rng.choice([1e-3, 1e-2, 0.1], count), lim.v_max)
    a_prev = -a_w + delta * rng.uniform(0, 1, count) ** 2
    peak = braking_peak_dense(v, np.maximum(a_prev - delta, -A), lim, T, integrator, n)
    d = np.maximum(peak, 0.0) * (1 + rng.choice([1e-7, 1e-3, 0.1, 1.0], count)) + 1e-12
    d = np.minimum(d, lim.q_max - lim.q_min)
    up = rng.uniform(size=count) < 0.5
    return [
        (lim.q_max - d[k], v[k], a_prev[k]) if up[k] else (lim.q_min + d[k], -v[k], -a_prev[k]) for k in range(count)
    ]


def lp_agreement(lim, T, integrator, n, states):
    """Compare the bounds with the LP on ``states``: a dict of the figures (see ``test_bounds_equal_the_lp``)."""
    q, v, a = (np.array(x) for x in zip(*states))
    lower, upper, viable = bounds64(lim, T, integrator, n, q, v, a, new_condition(integrator, n))
    samples = zoh_samples(lim, T) if integrator == "zoh" else 1
    res = lim.a_max * (T / samples) ** 2 / 8 if integrator == "zoh" else 0.0
    wide = JLimits1(lim.q_min - res, lim.q_max + res, lim.v_max, lim.a_max, lim.j_max)
    viable_wide = bounds64(wide, T, integrator, n, q, v, a, no_condition)[2]
    out = dict(states=len(states), lp_viable=0, mismatch=0, lp_resolution=0, excess=0.0, gap=0.0, bracket=0.0)
    for k in range(len(states)):
        r = lp_jerk_bounds_exact_first(float(q[k]), float(v[k]), float(a[k]), lim, T, integrator, n, samples=samples)
        if r is None:
            out["mismatch"] += int(bool(viable[k]))
            continue
        out["lp_viable"] += 1
        if not viable[k]:
            # the zoh LP samples positions: a state closer to the boundary than its resolution can be
            # LP-feasible and not viable; counted apart if it is viable with the limits that much wider
            out["lp_resolution" if integrator == "zoh" and viable_wide[k] else "mismatch"] += 1
            continue
        (o_lo, o_up), inner = r
        i_lo, i_up = inner if inner is not None else (o_lo, o_up)
        out["excess"] = max(out["excess"], upper[k] - o_up, o_lo - lower[k])
        out["gap"] = max(out["gap"], i_up - upper[k], lower[k] - i_lo)
        out["bracket"] = max(out["bracket"], o_up - i_up, i_lo - o_lo)
    return out


# ----------------------------------------------------------------------------- the envelope itself


def test_recovery_envelope_is_the_worst_recovery():
    """``travel``/``speed`` against a step-by-step simulation, and ``travel`` against a brute-force worst case.

    The simulation: the fastest recovery from the worst peak state (``-a_max`` from velocity 0, resp.
    ``h a_max``, then ``+delta`` per step), its deepest point and fastest backward speed. The worst
    case: ``peak(B_up(a)) + depth(B_lo(a))`` (what a conflict needs the range to be below) on a grid of
    ``(v, a)`` with both parts positive: never above ``travel``, and within 2 % of it.
    """
    rng = np.random.default_rng(3)
    for trial in range(40):
        A, T = rng.uniform(1, 30), 10 ** rng.uniform(-3, -0.7)
        J = A / T * 10 ** rng.uniform(-2.5, 0.3)
        integrator = ("zoh", "semi_implicit")[trial % 2]
        n = 1 if integrator == "zoh" else int(rng.integers(1, 7))
        h, delta = T / n, J * T
        lim = JLimits1(-1.0, 1.0, 1e3, A, J)
        env = jerk_condition.recovery_envelope(A, J, T, integrator, n)
        v0 = 0.0 if integrator == "zoh" else h * A
        depth = braking_peak_dense(np.array([-v0]), np.array([A]), lim, T, integrator, n)[0]
        np.testing.assert_allclose(env.travel, depth, rtol=1e-12)
        steps = np.arange(int(np.ceil(2 * A / delta)) + 3)
        speed = -np.min(v0 + T * np.cumsum(np.minimum(-A + steps * delta, A)))
        if integrator != "zoh" and speed <= h * A:  # no state moving up at >= h a_max can need it
            speed = 0.0
        np.testing.assert_allclose(env.speed, speed, rtol=1e-12, atol=1e-12 * A * T)
        if integrator != "zoh":  # v_max < h a_max: the worst peak state brakes with v_max / h only
            slow = jerk_condition.recovery_envelope(A, J, T, integrator, n, v_max=0.5 * h * A)
            depth = braking_peak_dense(np.array([-0.5 * h * A]), np.array([0.5 * A]), lim, T, integrator, n)[0]
            np.testing.assert_allclose(slow.travel, depth, rtol=1e-12)
        if trial < 12:
            vs = np.linspace(0.0, 1.2 * float(env.speed) + 2 * h * A, 301)
            V, Aa = (x.ravel() for x in np.meshgrid(vs, np.linspace(-A, A, 201)))
            P = braking_peak_dense(V, Aa, lim, T, integrator, n)
            Q = braking_peak_dense(-V, -Aa, lim, T, integrator, n)
            F = np.where((P >= 0) & (Q > 0), P + Q, -np.inf)
            assert np.max(F) <= env.travel * (1 + 1e-12), (np.max(F), env.travel)
            assert np.max(F) >= env.travel * 0.98, (np.max(F), env.travel)


def test_example_is_accepted_and_far_below_the_old_requirement():
    for integrator, n, travel, speed in (("zoh", 1, 0.388, 1.4), ("semi_implicit", 4, 0.285, 1.15)):
        env = jerk_condition.recovery_envelope(EXAMPLE.a_max, EXAMPLE.j_max, EXAMPLE_DT, integrator, n)
        np.testing.assert_allclose((env.travel, env.speed), (travel, speed), rtol=1e-12)
        CHECK(jl_limits(EXAMPLE), EXAMPLE_DT, integrator, n)
        span, v_need, _ = jerk_condition.jerk_condition_needs(jl_limits(EXAMPLE), EXAMPLE_DT, integrator, n)
        assert travel < span < travel * (1 + 1e-4) and speed < v_need < speed * (1 + 1e-4)  # the rounding margin


# ----------------------------------------------------------------------------- (a) exact where accepted

A_CASES = {
    "example-zoh": (EXAMPLE, EXAMPLE_DT, "zoh", 1),
    "example-semi4": (EXAMPLE, EXAMPLE_DT, "semi_implicit", 4),
    "edge-zoh": (edge_limits(10.0, 60.0, 0.1, "zoh", 1), 0.1, "zoh", 1),
    "edge-semi4": (edge_limits(10.0, 60.0, 0.1, "semi_implicit", 4), 0.1, "semi_implicit", 4),
    "edge-semi1": (edge_limits(10.0, 60.0, 0.1, "semi_implicit", 1, v_max=2.0), 0.1, "semi_implicit", 1),
    # v_max < h a_max (possible when no speed is needed): the worst peak brakes with v_max / h only
    "edge-semi1-slow": (edge_limits(10.0, 60.0, 0.1, "semi_implicit", 1, v_max=0.8), 0.1, "semi_implicit", 1),
    "edge-range-zoh-j200": (edge_limits(12.0, 200.0, 0.01, "zoh", 1, v_max=2.0), 0.01, "zoh", 1),
    "edge-semi5-j200": (edge_limits(12.0, 200.0, 0.01, "semi_implicit", 5), 0.01, "semi_implicit", 5),
}


@pytest.mark.parametrize("name", sorted(A_CASES))
def test_bounds_equal_the_lp(name):
    """Accepted, and on viable states the bounds are the LP's exact ones, within ``LP_TOL`` = 1e-9 rad/s^2.

    Zoh (``lp_jerk_bounds_exact_first``: the first step exact, later positions sampled
    ``zoh_samples`` times per step): never above the LP relaxation by more than ``LP_TOL``, never
    below its restriction (samples kept ``ZOH_RESOLUTION`` inside) by more; semi-implicit (exact LP):
    equal to ``LP_TOL``. Viability agrees with LP feasibility (zoh: but for states within the
    sampling resolution of the boundary, none so far). ``JERK_CONDITION_STATES`` random near-limit
    states plus as many of the tightest ones. Measured with 100 + 100 per case: no viability
    mismatch, at most 2.3e-13 above the relaxation and 6.7e-13 below the restriction (the zoh
    bracket itself, the LP's sampling: up to 4.8e-4 rad/s^2).
    """
    lim, T, integrator, n = A_CASES[name]
    CHECK(jl_limits(lim), T, integrator, n)  # accepted
    count = int(os.environ.get("JERK_CONDITION_STATES", "12"))
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    states = sample_states(lim, count, rng) + tight_states(lim, T, integrator, n, count, rng)
    res = lp_agreement(lim, T, integrator, n, states)
    assert res["mismatch"] == 0 and res["lp_viable"] >= count // 2, res
    assert res["excess"] <= LP_TOL and res["gap"] <= LP_TOL, res


# ----------------------------------------------------------------------------- (b) refused below, and failing there


def conflict_state(lim, T, integrator, n, kind, slack=1e-5):
    """The module docstring's state: ``q`` just under ``q_max``, ``v`` just above the worst peak's, ``a_prev = -a_w``.

    Returns ``(q, v, a_prev, a0_max)``: ``a0_max`` bounds every admissible first command, from the
    first step alone (which ``a_0`` fixes for every plan): zoh ``-v^2 / (2 d)`` (the parabola's vertex
    must stay under ``q_max``; for these ``v`` it is inside the step for every ``a_0`` near it),
    semi-implicit ``(d / h - v) / h`` (the first substep). ``kind="position"``: ``v`` small enough
    for the recovery to reach below ``q_min``; ``"velocity"``: for it to exceed ``v_max``.
    """
    A, h = lim.a_max, T / n
    env = jerk_condition.recovery_envelope(A, lim.j_max, T, integrator, n, v_max=lim.v_max)
    span = lim.q_max - lim.q_min
    # peak + depth falls from travel at the rate of the recovery's duration per unit of v: stay well inside
    margin = (float(env.travel) - span) if kind == "position" else (float(env.speed) - lim.v_max)
    assert margin > 0
    t_rec = 4 * A / lim.j_max + 2 * T
    dv = margin / (10 * t_rec) if kind == "position" else margin / 10
    a_w = A if integrator == "zoh" else min(A, (lim.v_max - dv) / h)
    v = dv if integrator == "zoh" else h * a_w + dv
    peak = float(braking_peak_dense(np.array([v]), np.array([-a_w]), lim, T, integrator, n)[0])
    q = lim.q_max - peak * (1 + slack)  # slack: room for the rounding of q_max - q
    d = lim.q_max - q  # exact (Sterbenz), the distance the bounds see
    a0_max = -v * v / (2 * d) if integrator == "zoh" else (d / h - v) / h
    return q, v, -a_w, a0_max


B_CASES = [
    (kind, integrator, n, rel, 2.0)
    for kind in ("position", "velocity")
    for integrator, n in (("zoh", 1), ("semi_implicit", 4), ("semi_implicit", 1))
    for rel in (1e-3, 1e-4)
    if not (kind == "velocity" and n == 1 and integrator == "semi_implicit")
]  # it needs no v_max (speed 0)
B_CASES += [("position", "semi_implicit", 1, 1e-3, 0.8)]  # v_max < h a_max: the travel of a_w = v_max / h


@pytest.mark.parametrize("kind,integrator,n,rel,v_max", B_CASES)
def test_refused_just_below_and_the_decoupling_fails_there(kind, integrator, n, rel, v_max):
    """``rel`` below the exact range (or v_max): a clear ValueError; and a state the per-side tests call viable is not.

    The state (``conflict_state``): ``viable`` is True for ``acc_bounds`` with the condition switched
    off, yet the LP relaxation has no plan whose first command respects the first step's own bound
    ``a0_max`` (necessary for every plan), so no admissible plan exists.
    """
    A, J, T = 10.0, 60.0, 0.1
    env = jerk_condition.recovery_envelope(A, J, T, integrator, n, v_max=v_max)
    if kind == "position":
        span = float(env.travel) * (1 - rel)
    else:
        span, v_max = 1.0, float(env.speed) * (1 - rel)
    lim = JLimits1(-span / 2, span / 2, v_max, A, J)
    two = jl.JointLimits([-0.5, lim.q_min], [0.5, lim.q_max], [2.0, lim.v_max], A, j_max=J)  # joint 0 is fine
    field = "q_max - q_min" if kind == "position" else "v_max"
    value, needed = (span, float(env.travel)) if kind == "position" else (v_max, float(env.speed))
    with pytest.raises(ValueError) as err:
        CHECK(two, T, integrator, n)
    msg = str(err.value)
    assert "joint 1:" in msg and "joint 0:" not in msg and field in msg, msg
    assert f"{value:.6g} < " in msg and f"< {needed:.4g}" in msg and "needed" in msg, msg
    other = "v_max" if kind == "position" else "q_max - q_min"
    assert f"{other} =" not in msg, msg  # only the failing field is named

    q, v, a_prev, a0_max = conflict_state(lim, T, integrator, n, kind)
    viable = bounds64(lim, T, integrator, n, [q], [v], [a_prev], no_condition)[2]
    assert bool(viable[0]), "the per-side tests should call the conflict state viable"
    samples = zoh_samples(lim, T) if integrator == "zoh" else 1
    assert not lp_jerk_feasible(q, v, a_prev, lim, T, integrator, n, samples=samples, first=(-A, a0_max))
    # at the needed values themselves the same state is viable and the LP agrees
    ok = edge_limits(A, J, T, integrator, n, v_max=v_max if kind == "position" else None)
    ok = ok if kind == "position" else JLimits1(-0.5, 0.5, ok.v_max, A, J)
    CHECK(jl_limits(ok), T, integrator, n)
    q_ok = ok.q_max - (lim.q_max - q)
    assert lp_jerk_feasible(q_ok, v, a_prev, ok, T, integrator, n, samples=samples, first=(-A, a0_max))
    assert bool(bounds64(ok, T, integrator, n, [q_ok], [v], [a_prev], new_condition(integrator, n))[2][0])


@pytest.mark.parametrize("kind", ["position", "velocity"])
@pytest.mark.parametrize("integrator,n", [("zoh", 1), ("semi_implicit", 4)])
def test_the_exact_values_are_tight_to_1e7(integrator, n, kind):
    """1e-7 below ``recovery_envelope``'s exact range (or v_max) the per-side tests still call a non-viable state viable.

    ``q_max = 0`` keeps ``q_max - q`` exact at the 1e-18 rad the zoh family needs there (its first-step
    peak, ``v^2 / (2 a_max)``, with ``v ~ 1e-9`` rad/s). So the condition is exactly tight up to its
    float32 rounding margin (``jerk_condition_needs``), measured here to 1e-7.
    """
    A, J, T, rel = 10.0, 60.0, 0.1, 1e-7
    env = jerk_condition.recovery_envelope(A, J, T, integrator, n)
    if kind == "position":
        lim = JLimits1(-float(env.travel) * (1 - rel), 0.0, 2.0, A, J)
    else:
        lim = JLimits1(-1.0, 0.0, float(env.speed) * (1 - rel), A, J)
    q, v, a_prev, a0_max = conflict_state(lim, T, integrator, n, kind, slack=1e-9)
    assert bool(bounds64(lim, T, integrator, n, [q], [v], [a_prev], no_condition)[2][0])
    samples = 2 * zoh_samples(lim, T) if integrator == "zoh" else 1
    assert not lp_jerk_feasible(q, v, a_prev, lim, T, integrator, n, samples=samples, first=(-A, a0_max))


# ----------------------------------------------------------------------------- rollouts at the edge


def rollout(lim, T, integrator, n, policy, dtype, condition, steps=150, count=16, seed=0):
    """Worst violations of ``policy`` riding the bounds (rounding guard on) from rest, ``count`` joints."""
    rng = np.random.default_rng(seed)
    span = lim.q_max - lim.q_min
    q = (lim.q_min + span * rng.uniform(0.3, 0.7, count)).astype(dtype)
    v, a_prev = np.zeros(count, dtype), np.zeros(count, dtype)
    switch = rng.integers(2, 12, count)
    worst = dict(position=0.0, velocity=0.0, jerk=0.0, nonviable=0)
    with use_condition(condition), jax.enable_x64(dtype == np.float64):
        for k in range(steps):
            b = jl.acc_bounds(q, v, jl_limits(lim), T, method="jerk", integrator=integrator, substeps=n, a_prev=a_prev)
            lower, upper = np.asarray(b.lower), np.asarray(b.upper)
            worst["nonviable"] += int(np.sum(~np.asarray(b.viable)))
            if policy == "upper":
                a = upper
            elif policy == "lower":
                a = lower
            else:
                a = np.where((k // switch) % 2 == 0, upper, lower)
            a = a.astype(dtype)
            worst["jerk"] = max(worst["jerk"], float(np.max(np.abs(a.astype(np.float64) - a_prev) - lim.j_max * T)))
            q, v, q_lo, q_hi = simulate_step(q, v, a, T, integrator, n, dtype)
            a_prev = a
            worst["position"] = max(worst["position"], float(np.max(q_hi - lim.q_max)), float(np.max(lim.q_min - q_lo)))
            worst["velocity"] = max(worst["velocity"], float(np.max(np.abs(v.astype(np.float64)) - lim.v_max)))
    return worst


@pytest.mark.parametrize("name", ["edge-zoh", "edge-semi4", "edge-semi1-slow"])
def test_rollouts_at_the_edge_never_violate(name, dtype):
    """At the needed range and v_max, riding the bounds (up, down, bang-bang) keeps every limit, float32 too."""
    lim, T, integrator, n = A_CASES[name]
    tol = 1e-6 if dtype == np.float32 else 1e-12
    for policy in ("upper", "lower", "bang_bang"):
        worst = rollout(lim, T, integrator, n, policy, dtype, new_condition(integrator, n))
        assert worst["position"] <= tol and worst["velocity"] <= tol * lim.v_max, (policy, worst)
        assert worst["jerk"] <= 4e-6 * lim.a_max and worst["nonviable"] == 0, (policy, worst)


@pytest.mark.parametrize("integrator,n", [("zoh", 1), ("semi_implicit", 4)])
def test_rollouts_just_below_the_condition_leave_the_limits(integrator, n):
    """0.1 % below the needed range (the condition switched off): bang-bang riding the bounds from rest goes out.

    The same rollout at the needed range keeps every limit (``test_rollouts_at_the_edge_never_violate``);
    here it reaches a conflict state (called viable, not viable) and leaves the range by ~1e-4 rad.
    """
    env = jerk_condition.recovery_envelope(10.0, 60.0, 0.1, integrator, n)
    span = float(env.travel) * (1 - 1e-3)
    lim = JLimits1(-span / 2, span / 2, 2.0, 10.0, 60.0)
    worst = rollout(lim, 0.1, integrator, n, "bang_bang", np.float64, no_condition, steps=100)
    assert worst["position"] > 1e-5 and worst["nonviable"] > 0, worst


# ----------------------------------------------------------------------------- inputs


def test_input_rules():
    with pytest.raises(ValueError, match="j_max"):
        CHECK(jl.JointLimits(-1.0, 1.0, 2.0, 10.0), 0.01)
    with pytest.raises(ValueError, match="integrator"):
        CHECK(jl_limits(EXAMPLE), 0.1, "rk4")
    with pytest.raises(ValueError, match="substeps"):
        CHECK(jl_limits(EXAMPLE), 0.1, "zoh", 2)
    with pytest.raises(ValueError, match="dt"):
        CHECK(jl_limits(EXAMPLE), -0.1)
    too_small = jl.JointLimits(-0.01, 0.01, 2.0, 12.0, j_max=20.0)
    with pytest.raises(ValueError, match="recover"):
        CHECK(too_small, 0.01)
    jax.jit(lambda dt: CHECK(too_small, dt) or dt)(0.01)  # traced dt: nothing to check eagerly
    jax.jit(lambda lo: CHECK(jl.JointLimits(lo, 0.01, 2.0, 12.0, j_max=20.0), 0.01) or lo)(-0.01)


if __name__ == "__main__":
    for name in sorted(A_CASES):
        lim, T, integrator, n = A_CASES[name]
        count = int(os.environ.get("JERK_CONDITION_STATES", "100"))
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        states = sample_states(lim, count, rng) + tight_states(lim, T, integrator, n, count, rng)
        print(name, lim, lp_agreement(lim, T, integrator, n, states), flush=True)
