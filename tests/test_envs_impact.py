"""Wall strike (MJX Panda): with the impact caps the measured impulsive torques stay within bounds,
without them they do not. One small batch, one compilation (the full run: benchmarks/impact_strikes.py)."""

import jax
import numpy as np
import pytest

from jaxlimits.envs.arm import make_planar_reach
from jaxlimits.envs.safety import SafetyWrapper
from jaxlimits.envs.wall_strike import make_wall_strike, strike_experiment


@pytest.fixture(scope="module")
def env():
    return make_wall_strike(torque_samples=5000, gap_low=0.005, gap_high=0.02)


def test_strikes_with_and_without_caps(env):
    shields = [SafetyWrapper(env, "viability"), SafetyWrapper(env, "viability", impact=True)]
    r = strike_experiment(env, shields, batch=4, steps=45, speed_range=(0.8, 1.5), seed=3)
    free, capped = r["viability"], r["viability+impact"]
    # every strike reaches the wall (gaps <= 2 cm)
    assert np.all(free["hit"] > 0) and np.all(capped["hit"] > 0)
    # without the caps: the impulsive torque bound is violated (the strikes are fast)
    assert np.all(free["tau"] > 1.0), free["tau"]
    assert np.all(np.isinf(free["cap"]))
    # with them: the contact speed is at most the cap, the measured impulsive torques and the
    # post-impact joint velocities are within their bounds, no other limit is violated
    assert np.all(capped["w"] <= capped["cap"] * 1.02 + 1e-3), (capped["w"], capped["cap"])
    assert np.all(capped["tau"] <= 1.0), capped["tau"]
    assert np.all(capped["v_post"] <= 1.0)
    for k in ("violation_position", "violation_velocity", "violation_torque"):
        assert np.all(capped[k] == 0.0), (k, capped[k])
    assert np.all(capped["cap"] > 0.02) and np.all(capped["cap"] < 0.3)
    assert np.all(free["w"] > capped["w"])


def test_wrapper_structure_and_errors(env):
    """reset and step give the same pytree (Brax needs it); impact= needs an impact-capable env."""
    w = SafetyWrapper(env, "viability", impact={"margin": 0.9, "c_range": (0.0, 0.5)})
    assert w.name == "viability+impact"
    s0 = jax.eval_shape(w.reset, jax.random.PRNGKey(0))
    s1 = jax.eval_shape(w.step, s0, jax.ShapeDtypeStruct((env.n,), np.float32))
    assert jax.tree.structure(s0) == jax.tree.structure(s1)
    assert {"impact_cap", "impact_infeasible", "impact/tau", "impact/w", "impact/v_post"} <= set(s1.metrics)
    with pytest.raises(ValueError, match="impact"):
        SafetyWrapper(make_planar_reach(torque_samples=0), "viability", impact=True)
    with pytest.raises(ValueError, match="unknown options"):
        SafetyWrapper(env, "viability", impact={"bogus": 1})
    with pytest.raises(ValueError, match="restitution"):
        SafetyWrapper(env, "viability", impact={"c_range": (0.5, 0.1)})
    with pytest.raises(ValueError, match="margin"):
        SafetyWrapper(env, "viability", impact={"margin": 0.0})
