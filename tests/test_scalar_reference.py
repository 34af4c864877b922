"""jaxlimits' bounds against the scalar transcription of Del Prete 2018 (benchmarks/scalar_reference.py).

Two independent checks on random *viable* states, half of them crowded near the position limits,
on the viability curve ``d = D(v)`` (``D(v) = v^2 / (2 a_max)`` for the zero-order hold, the
discrete braking distance for semi-implicit Euler), on the velocity limit, at rest and on the
branch boundary ``2 d = dt v`` of Alg. 1:

1. ``jl.acc_bounds(..., rounding_guard=False)`` equals ``scalar_bounds`` within ``1e-9 a_max``:
   for the zero-order hold that is the paper's Algorithms 1-3 transcribed literally; for the
   semi-implicit model a scalar port of ``semi_implicit.py`` (so check 2 is what makes that one
   independent).
2. Both equal the definition, problem (12): the largest (smallest) ``a`` such that the position
   stays within its limits for all ``t in [0, dt]`` (zoh) or at every substep (semi-implicit), the
   next velocity within its limit and the next state viable. Each constraint of (12) is monotone
   in ``a`` (the upper-side ones are down-sets, the lower-side ones up-sets), so the supremum is the
   bisection point of the upper-side predicate, clipped to ``[-a_max, a_max]``. The predicate is
   evaluated by direct simulation of the step (the parabola's extremum for zoh, the substep
   recursion for semi-implicit) in exact rational arithmetic (``fractions.Fraction``), so no
   rounding and no conditioning issue enters the reference; the bisection stops at ``1e-11 a_max``.

No disagreement between the literal paper and the library was found on these configurations
(differences are <= 4e-13 a_max, from the paper's quadratic-formula root (28) at dt = 0.01), and
the paper's bounds equal the definition (12) everywhere sampled, so there is no discrepancy class
to document here.
"""

from __future__ import annotations

import math
import sys
from fractions import Fraction
from pathlib import Path

import jax
import numpy as np
import pytest

import jaxlimits as jl

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
from scalar_reference import scalar_bounds  # noqa: E402

# (q_min, q_max, v_max, a_max), dt, integrator, substeps
CONFIGS = [
    ((-0.5, 0.5, 2.0, 10.0), 0.1, "zoh", 1),  # the paper's Fig. 3
    ((-2.0, 2.0, 2.0, 12.0), 0.01, "zoh", 1),
    # condition (11) tight: span = 0.1 ~ a_max dt^2. a_max = 10 (equality) is refused by acc_bounds
    # (CONDITION_11_SLACK = 1e-4); 9.998 is the largest round value it accepts.
    ((-0.05, 0.05, 1.0, 9.998), 0.1, "zoh", 1),
    ((-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 1),
    ((-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 5),
    ((-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 10),
]
# The definition check needs no acc_bounds, so it also covers (11) at exact equality: the paper's
# claim V = V^c (and so the exactness of Alg. 1-3) holds there too.
CONFIGS_12 = CONFIGS + [((-0.05, 0.05, 1.0, 10.0), 0.1, "zoh", 1)]


def _id(cfg):
    lim, dt, integ, sub = cfg
    return f"{integ}{sub}-span{lim[1] - lim[0]:g}-amax{lim[3]:g}-dt{dt:g}"


N_DRAW = 4000  # states drawn per configuration (before the viability filter)
N_EXACT = 150  # states per configuration checked against the exact definition (12)
TOL = 1e-9  # relative to a_max


# ---------------------------------------------------------------- sampling


def _braking_distance_np(v, a_max, integrator, h):
    """Distance to stop under full braking (vectorised, float64): the viability curve is d = D(v)."""
    vp = np.maximum(v, 0.0)
    if integrator == "zoh":
        return vp * vp / (2.0 * a_max)
    K = np.floor(vp / (a_max * h))
    return h * (K * vp - a_max * h * K * (K + 1.0) / 2.0)


def draw_states(rng, lim, dt, integrator, substeps, n):
    """``n`` candidate states, half near the limits and the curves (first), half uniform over the box.

    Returns ``q, v, viable, near``: the states, ``jl.is_viable`` of each (same model, float64) and
    whether it is one of the near-limit half. All ``n`` are returned (and the library is evaluated
    on all of them, comparing only the viable ones) so that every configuration has the same array
    shape and JAX's eager op cache is reused across the configurations.
    """
    q_min, q_max, v_max, a_max = lim
    span, h = q_max - q_min, dt / substeps
    m = n // 2
    kind = rng.integers(0, 6, m)
    tiny = 10.0 ** rng.uniform(-16, -1, m)  # relative offsets from a boundary
    d_any = span * 10.0 ** rng.uniform(-15, 0, m) * (rng.random(m) > 0.1)  # 10 % exactly on the limit
    v_any = v_max * rng.random(m)
    # on / just inside the viability curve, starting from a velocity
    d_curve = _braking_distance_np(v_any, a_max, integrator, h) * np.where(rng.random(m) < 0.2, 1.0, 1.0 + tiny)
    # on / just inside the viability curve, starting from a distance (zoh: v = sqrt(2 a d))
    v_curve = np.sqrt(2.0 * a_max * d_any) * np.where(rng.random(m) < 0.2, 1.0, 1.0 - tiny)
    # at the velocity limit
    v_lim = v_max * np.where(rng.random(m) < 0.3, 1.0, 1.0 - tiny)
    d = np.select(
        [kind == 0, kind == 1, kind == 2, kind == 3, kind == 4],
        [d_curve, d_any, d_any, d_any, _braking_distance_np(v_lim, a_max, integrator, h) * (1.0 + tiny)],
        d_any,
    )
    v = np.select(
        [kind == 0, kind == 1, kind == 2, kind == 3, kind == 4],
        [v_any, v_curve, 0.0 * d_any, -v_any, v_lim],
        2.0 * d_any / dt * (1.0 + rng.normal(0.0, 1e-6, m)),  # Alg. 1's branch boundary 2 d = dt v
    )
    side = rng.choice([-1.0, 1.0], m)
    q_near = np.where(side > 0, q_max - d, q_min + d)
    q = np.concatenate([q_near, rng.uniform(q_min, q_max, n - m)])
    v = np.concatenate([side * v, rng.uniform(-v_max, v_max, n - m)])
    viable = np.asarray(jl.is_viable(q, v, jl.JointLimits(*lim), integrator=integrator, dt=dt, substeps=substeps))
    near = np.arange(n) < m
    return q, v, viable, near


# ---------------------------------------------------------------- the definition (12), exactly


def _exact_braking_distance(x, a_max, integrator, h):
    if x <= 0:
        return Fraction(0)
    if integrator == "zoh":
        return x * x / (2 * a_max)
    K = math.floor(x / (a_max * h))
    return h * (K * x - a_max * h * K * (K + 1) / 2)


def _exact_upper_ok(a, d, v, v_max, a_max, dt, integrator, n):
    """Upper-side constraints of (12) for acceleration ``a``, state at distance ``d`` below q_max.

    Every argument is a Fraction; the step is simulated exactly.
    """
    if integrator == "zoh":
        if dt * v + dt * dt * a / 2 > d:  # end of the step
            return False
        if a < 0 and 0 < -v / a < dt and -v * v / (2 * a) > d:  # the parabola's peak inside the step
            return False
        d1, v1 = d - dt * v - dt * dt * a / 2, v + dt * a
        h = None
    else:
        h = dt / n
        travel, vk = Fraction(0), v
        for _ in range(n):  # semi-implicit Euler substeps
            vk = vk + h * a
            travel = travel + h * vk
            if travel > d:
                return False
        d1, v1 = d - travel, vk
    if v1 > v_max:
        return False
    return _exact_braking_distance(v1, a_max, integrator, h) <= d1


def exact_sup(d, v, v_max, a_max, dt, integrator, n):
    """``min(sup{a : upper-side constraints hold}, a_max)`` by bisection on the exact predicate."""
    d, v, v_max, a_max, dt = (Fraction(x) for x in (d, v, v_max, a_max, dt))

    def ok(a):
        return _exact_upper_ok(Fraction(a), d, v, v_max, a_max, dt, integrator, n)

    a_hi = float(a_max)
    if ok(a_hi):
        return a_hi
    a_lo = -float(a_max)
    # (12) is feasible at every viable state (condition 11), so the down-set contains -a_max
    assert ok(a_lo), "the upper-side constraints of (12) exclude -a_max at a viable state"
    while a_hi - a_lo > 1e-11 * float(a_max):
        mid = 0.5 * (a_lo + a_hi)
        if ok(mid):
            a_lo = mid
        else:
            a_hi = mid
    return 0.5 * (a_lo + a_hi)


def exact_viable(q, v, lim, integrator, h):
    q_min, q_max, v_max, a_max = (Fraction(x) for x in lim)
    q, v = Fraction(q), Fraction(v)
    if not (q_min <= q <= q_max and abs(v) <= v_max):
        return False
    return (
        _exact_braking_distance(v, a_max, integrator, h) <= q_max - q
        and _exact_braking_distance(-v, a_max, integrator, h) <= q - q_min
    )


# ---------------------------------------------------------------- tests


@pytest.mark.parametrize("lim, dt, integrator, substeps", CONFIGS, ids=[_id(c) for c in CONFIGS])
def test_library_equals_scalar_reference(lim, dt, integrator, substeps):
    rng = np.random.default_rng(2018 + substeps + int(1000 * dt))
    with jax.enable_x64(True):
        q_all, v_all, viable, near = draw_states(rng, lim, dt, integrator, substeps, N_DRAW)
        assert np.count_nonzero(viable) > 2500 and np.count_nonzero(viable & near) > 1200
        q, v = q_all[viable], v_all[viable]
        limits = jl.JointLimits(*lim)
        for method in ("viability", "naive"):
            b = jl.acc_bounds(
                q_all, v_all, limits, dt, method=method, integrator=integrator, substeps=substeps, rounding_guard=False
            )
            lower, upper = np.asarray(b.lower)[viable], np.asarray(b.upper)[viable]
            assert lower.dtype == np.float64
            ref = np.array(
                [
                    scalar_bounds(qi, vi, *lim, dt, method=method, integrator=integrator, substeps=substeps)
                    for qi, vi in zip(q.tolist(), v.tolist())
                ]
            )
            err = np.maximum(np.abs(ref[:, 0] - lower), np.abs(ref[:, 1] - upper)) / lim[3]
            worst = int(np.argmax(np.where(np.isnan(err), np.inf, err)))
            assert np.all(err <= TOL), (
                f"{method}: q={q[worst]!r} v={v[worst]!r} library=({lower[worst]!r}, {upper[worst]!r}) "
                f"reference={tuple(ref[worst])!r}"
            )
            if method == "viability":
                assert np.all(np.asarray(b.viable)[viable])
                # the paper's interval is never empty at a viable state (up to roundoff)
                assert np.all(ref[:, 0] <= ref[:, 1] + TOL * lim[3])


@pytest.mark.parametrize("lim, dt, integrator, substeps", CONFIGS_12, ids=[_id(c) for c in CONFIGS_12])
def test_scalar_reference_equals_definition_12(lim, dt, integrator, substeps):
    """The paper's (and the port's) bounds are the exact optimum of (12), by direct simulation."""
    rng = np.random.default_rng(12 + substeps + int(1000 * dt))
    q_min, q_max, v_max, a_max = lim
    h = Fraction(dt) / substeps
    with jax.enable_x64(True):
        q, v, viable, near = draw_states(rng, lim, dt, integrator, substeps, N_DRAW)
    idx = np.concatenate([np.flatnonzero(viable & near)[:100], np.flatnonzero(viable & ~near)[: N_EXACT - 100]])
    checked = 0
    for i in idx:
        qi, vi = float(q[i]), float(v[i])
        if not exact_viable(qi, vi, lim, integrator, h):  # float is_viable can pass a state 1 ulp outside
            continue
        lower, upper = scalar_bounds(qi, vi, *lim, dt, method="viability", integrator=integrator, substeps=substeps)
        # q_max - q and q - q_min as exact rationals (Fraction(q_max) - Fraction(q), not the float difference)
        sup = exact_sup(Fraction(q_max) - Fraction(qi), Fraction(vi), v_max, a_max, dt, integrator, substeps)
        inf = -exact_sup(Fraction(qi) - Fraction(q_min), -Fraction(vi), v_max, a_max, dt, integrator, substeps)
        assert abs(upper - sup) <= TOL * a_max, (qi, vi, upper, sup)
        assert abs(lower - inf) <= TOL * a_max, (qi, vi, lower, inf)
        checked += 1
    assert checked >= 0.9 * len(idx), (checked, len(idx))
