"""Exactness against an independent reference: a long-horizon linear program (scipy HiGHS).

The LP maximises / minimises the first acceleration subject to every future limit (``reference.
lp_bounds``); its optimum is the exact answer of Del Prete's problem (4) for the model. The closed
form (``rounding_guard=False``, float64) must agree with it on viable states, and the LP must be
infeasible exactly where ``viable`` is False. ``JAXLIMITS_LP_STATES`` raises the number of states
per configuration (default 60; the README reports a larger run).
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlimits as jl
from reference import Limits1, certified_safe, lp_bounds, viable_reference

STATES = int(os.environ.get("JAXLIMITS_LP_STATES", "60"))

CONFIGS = {
    "fig3-zoh": (Limits1(-0.5, 0.5, 2.0, 10.0), 0.1, "zoh", 1),
    "fig4-zoh": (Limits1(-2.0, 2.0, 2.0, 12.0), 0.01, "zoh", 1),
    "near11-zoh": (Limits1(-0.05, 0.05, 1.0, 9.99), 0.1, "zoh", 1),
    "fig4-semi1": (Limits1(-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 1),
    "fig4-semi5": (Limits1(-2.0, 2.0, 2.0, 12.0), 0.01, "semi_implicit", 5),
    "fig3-semi4": (Limits1(-0.5, 0.5, 2.0, 10.0), 0.1, "semi_implicit", 4),
    "near11-semi7": (Limits1(-0.05, 0.05, 1.0, 9.99), 0.1, "semi_implicit", 7),
    "asym-semi10": (Limits1(-0.3, 1.7, 1.5, 20.0), 0.02, "semi_implicit", 10),
}

# HiGHS runs at 1e-10 feasibility; the zoh cutting planes stop once no step exceeds a limit by
# more than 1e-9 rad (reference.lp_bounds).
LP_POSITION_TOL = 1e-9


def sample_states(lim: Limits1, count: int, rng) -> list[tuple[float, float]]:
    """States near the limits, near the viability curve, a few beyond it, and anywhere."""
    span = lim.q_max - lim.q_min
    out = []
    for i in range(count):
        kind = i % 4
        d = span * rng.uniform() ** (4 if kind < 2 else 1)
        cap = min(lim.v_max, math.sqrt(2 * lim.a_max * d))
        if kind == 0:
            v = cap * rng.uniform(-1, 1)
        elif kind == 1:
            v = cap * (1 + 0.03 * rng.uniform(-1, 1))
        elif kind == 2:
            v = cap * (1 + 0.2 * rng.uniform(-1, 1))
        else:
            v = lim.v_max * rng.uniform(-1.05, 1.05)
        out.append((lim.q_max - d, v) if rng.uniform() < 0.5 else (lim.q_min + d, -v))
    return out


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_closed_form_equals_long_horizon_lp(name, x64):
    lim, T, integrator, n = CONFIGS[name]
    limits = jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max)
    states = sample_states(lim, STATES, np.random.default_rng(7))
    q = jnp.array([s[0] for s in states])
    v = jnp.array([s[1] for s in states])

    def bounds(q):
        return jl.acc_bounds(q, v, limits, T, integrator=integrator, substeps=n, rounding_guard=False)

    b = bounds(q)
    # The zoh LP may break a position limit by LP_POSITION_TOL somewhere; that is the same as a limit
    # LP_POSITION_TOL further away, which moves the bound by |d bound / d q| times it (large where
    # the position peaks inside the step right next to the limit: there it is a / d).
    slope_up = jnp.abs(jax.jacfwd(lambda q: bounds(q).upper.sum())(q))
    slope_lo = jnp.abs(jax.jacfwd(lambda q: bounds(q).lower.sum())(q))
    lp_slack = LP_POSITION_TOL if integrator == "zoh" else 0.0
    compared, lp_degenerate = 0, []
    for i, (qi, vi) in enumerate(states):
        ref = lp_bounds(qi, vi, lim, T, integrator, n)
        viable = bool(b.viable[i])
        # at the exact boundary the LP and the closed form may round either way
        on_edge = viable_reference(qi, vi, lim, integrator, T, n, tol=1e-10) != viable_reference(
            qi, vi, lim, integrator, T, n, tol=-1e-10
        )
        if on_edge:
            continue
        lo, up = float(b.lower[i]), float(b.upper[i])
        if viable and ref is None:  # the LP gave up on a degenerate boundary: demand a proof instead
            assert certified_safe(qi, vi, up, lim, T, integrator, n), (name, qi, vi, up)
            lp_degenerate.append((qi, vi))
            continue
        assert viable == (ref is not None), (name, qi, vi, viable, ref)
        if ref is None:
            continue
        compared += 1
        # safe: never wider than the LP optimum, or else proven safe by an explicit plan
        for mine, lp, side in ((up, ref[1], 1.0), (lo, ref[0], -1.0)):
            if side * (mine - lp) > 1e-9 * lim.a_max:
                assert certified_safe(qi, vi, mine, lim, T, integrator, n), (name, qi, vi, lo, up, ref)
                lp_degenerate.append((qi, vi))
        # exact: never narrower than the LP optimum beyond the LP's own tolerance
        tol_up = 1e-9 * lim.a_max + lp_slack * (2 / T**2 + float(slope_up[i]))
        tol_lo = 1e-9 * lim.a_max + lp_slack * (2 / T**2 + float(slope_lo[i]))
        assert up >= ref[1] - tol_up and lo <= ref[0] + tol_lo, (name, qi, vi, lo, up, ref)
    assert compared >= STATES // 2, compared
    assert len(lp_degenerate) <= max(2, STATES // 20), lp_degenerate


def test_lp_reference_is_not_trivially_agreeable(x64):
    """The reference distinguishes models: zoh bounds are wrong for the semi-implicit LP."""
    lim, T = Limits1(-2.0, 2.0, 2.0, 12.0), 0.01
    limits = jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max)
    q, v = 1.9, 1.5
    zoh = jl.acc_bounds(jnp.float64(q), jnp.float64(v), limits, T, rounding_guard=False)
    semi_ref = lp_bounds(q, v, lim, T, "semi_implicit", 5)
    assert abs(float(zoh.upper) - semi_ref[1]) > 1e-3


@pytest.mark.parametrize("integrator, n", [("zoh", 1), ("semi_implicit", 5)])
def test_safety_certificate_can_refuse(integrator, n, x64):
    """The certificate accepts the exact bound and refuses a hair more."""
    lim, T = Limits1(-2.0, 2.0, 2.0, 12.0), 0.01
    limits = jl.JointLimits(lim.q_min, lim.q_max, lim.v_max, lim.a_max)
    for q, v in ((1.9, 1.5), (1.99, 0.3), (-1.95, -1.0)):
        b = jl.acc_bounds(
            jnp.float64(q), jnp.float64(v), limits, T, integrator=integrator, substeps=n, rounding_guard=False
        )
        up, lo = float(b.upper), float(b.lower)
        assert certified_safe(q, v, up, lim, T, integrator, n) and certified_safe(q, v, lo, lim, T, integrator, n)
        if up < lim.a_max:
            assert not certified_safe(q, v, up + 1e-5, lim, T, integrator, n)
        if lo > -lim.a_max:
            assert not certified_safe(q, v, lo - 1e-5, lim, T, integrator, n)
