"""SafetyWrapper and ArmReach: Brax contract, limits read from the model, jit/vmap, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import jaxlimits as jl
from jaxlimits.envs.arm import VIOLATION_KEYS, make_planar_reach
from jaxlimits.envs.safety import SafetyWrapper


@pytest.fixture(scope="module")
def env():
    return make_planar_reach()


@pytest.fixture(scope="module")
def rollout(env):
    w = SafetyWrapper(env, "viability")

    @jax.jit
    def run(keys):
        s0 = jax.vmap(w.reset)(keys)

        def body(s, _):
            s = jax.vmap(w.step)(s, jnp.ones((keys.shape[0], env.n), jnp.float32))
            return s, (s.metrics, s.pipeline_state.qpos)

        return jax.lax.scan(body, s0, None, length=300)

    return w, run(jax.random.split(jax.random.PRNGKey(1), 2))


def test_limits_come_from_the_model(env):
    m = env.mj_model
    np.testing.assert_array_equal(env.limits.q_min, m.jnt_range[:, 0])
    np.testing.assert_array_equal(env.limits.q_max, m.jnt_range[:, 1])
    np.testing.assert_array_equal(env.tau_max, m.actuator_ctrlrange[:, 1])
    assert env.dt == pytest.approx(m.opt.timestep * 5)
    assert env.integrator == "semi_implicit"
    # the joint-limit constraint stays in the model and is disabled in the simulation
    assert not m.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_LIMIT
    assert env.sys.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_LIMIT
    assert env.torque_scale > 1.0  # planar arm: the nominal a_max needs no more than the motors give


def test_wrapper_metrics_and_full_push(rollout, env):
    w, (s, (metrics, qs)) = rollout
    for k in VIOLATION_KEYS:
        assert f"violation/{k}" in metrics and f"count/{k}" in metrics
    assert "intervention" in metrics and "viable" in metrics
    assert float(jnp.max(metrics["violation/position"])) == 0.0
    assert float(jnp.max(metrics["violation/velocity"])) == 0.0
    assert bool(jnp.all(metrics["viable"] == 1.0))
    # pushed at full acceleration, the joints end up at (not past) their upper limits
    q_end = np.asarray(qs[-1])
    assert np.all(q_end <= env.limits.q_max) and np.all(q_end > env.limits.q_max - 0.05)
    assert float(jnp.max(metrics["intervention"])) > 0.0


def test_bounds_use_the_env_discretisation(rollout, env):
    w, (s, _) = rollout  # batched final states of the rollout
    b = w.bounds(s)
    ref = jl.acc_bounds(s.pipeline_state.qpos, s.pipeline_state.qvel, env.limits, env.dt,
                        integrator="semi_implicit", substeps=env.frame_skip)
    np.testing.assert_array_equal(b.lower, ref.lower)
    np.testing.assert_array_equal(b.upper, ref.upper)


def test_bad_configuration_raises(env):
    with pytest.raises(ValueError, match="method"):
        SafetyWrapper(env, "magic")
    with pytest.raises(TypeError):
        SafetyWrapper(object(), "clip")
