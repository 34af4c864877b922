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
    ref = jl.acc_bounds(
        s.pipeline_state.qpos,
        s.pipeline_state.qvel,
        env.limits,
        env.dt,
        integrator="semi_implicit",
        substeps=env.frame_skip,
    )
    np.testing.assert_array_equal(b.lower, ref.lower)
    np.testing.assert_array_equal(b.upper, ref.upper)


def test_bad_configuration_raises(env):
    with pytest.raises(ValueError, match="method"):
        SafetyWrapper(env, "magic")
    with pytest.raises(TypeError):
        SafetyWrapper(object(), "clip")


# ---- Brax training wrappers (VmapWrapper -> EpisodeWrapper -> AutoResetWrapper) ------------------
EPISODE = 5


@pytest.fixture(scope="module")
def brax_run(env):
    """``SafetyWrapper(viability, torque_box=True)`` under ``brax.envs.wrappers.training.wrap``: 4 envs, 2 episodes + 1 step.

    The torque box is on so that one compilation covers it too (on the planar arm it never binds:
    the nominal ``a_max`` needs at most 1/1.86 of the motors' torque).
    """
    from brax.envs.wrappers import training

    w = SafetyWrapper(env, "viability", torque_box=True)
    benv = training.wrap(w, episode_length=EPISODE, action_repeat=1)
    reset, step = jax.jit(benv.reset), jax.jit(benv.step)
    s = reset(jax.random.split(jax.random.PRNGKey(2), 4))
    action = jnp.broadcast_to(jnp.asarray([1.0, -1.0, 1.0], jnp.float32), (4, env.n))
    states = [s]
    for _ in range(2 * EPISODE + 1):
        states.append(step(states[-1], action))
    return w, states


def test_brax_training_wrap_truncates_and_autoresets(brax_run, env):
    w, states = brax_run
    s0 = states[0]
    assert s0.obs.shape == (4, env.observation_size) and s0.pipeline_state.qpos.shape == (4, env.n)
    for t, s in enumerate(states[1:], start=1):
        ended = t % EPISODE == 0
        np.testing.assert_array_equal(s.done, float(ended))
        np.testing.assert_array_equal(s.info["truncation"], float(ended))  # done by the time limit only
        np.testing.assert_array_equal(s.info["steps"], (t - 1) % EPISODE + 1)
        if ended:  # AutoResetWrapper: back to the episode's first state
            np.testing.assert_array_equal(s.pipeline_state.qpos, s0.pipeline_state.qpos)
            np.testing.assert_array_equal(s.obs, s0.obs)
        else:
            assert np.all(np.asarray(s.pipeline_state.qpos) != np.asarray(s0.pipeline_state.qpos))


def test_brax_training_wrap_accumulates_episode_metrics(brax_run):
    w, states = brax_run
    ep = [s.info["episode_metrics"] for s in states]
    for key in ("intervention", "count/position", "violation/velocity", "torque_box_conflict", "viable", "distance"):
        assert key in ep[0]
    # episode sums of the per-step metrics, restarted after each episode end
    total = sum(np.asarray(s.metrics["intervention"]) for s in states[1 : EPISODE + 1])
    np.testing.assert_allclose(ep[EPISODE]["intervention"], total, rtol=1e-5)
    dist = sum(np.asarray(s.metrics["distance"]) for s in states[1 : EPISODE + 1])
    np.testing.assert_allclose(ep[EPISODE]["distance"], dist, rtol=1e-5)
    assert np.all(dist > 0)
    np.testing.assert_array_equal(ep[EPISODE]["length"], EPISODE)
    np.testing.assert_array_equal(ep[EPISODE + 1]["length"], 1)
    np.testing.assert_allclose(ep[EPISODE + 1]["intervention"], states[EPISODE + 1].metrics["intervention"], rtol=1e-6)
    np.testing.assert_array_equal(ep[EPISODE]["viable"], EPISODE)
    for k in VIOLATION_KEYS:
        if k != "jerk":  # the viability shield does not bound jerk
            np.testing.assert_array_equal(ep[2 * EPISODE][f"count/{k}"], 0.0)


def test_torque_box_on_the_planar_arm_never_binds(brax_run, env):
    """Same bounds as without the box (box scale > 1 at every visited state); the box is ``torque_acc_box_conservative``."""
    from jaxlimits._src import torque

    w, states = brax_run
    plain = jax.jit(SafetyWrapper(env, "viability").bounds)
    for prev, s in zip(states[:3], states[1:4]):  # info["lower"/"upper"]: the bounds of the step that led to s
        assert np.all(np.asarray(s.metrics["torque_box_scale"]) > 1.0)
        np.testing.assert_array_equal(s.metrics["torque_box_conflict"], 0.0)
        b0 = plain(prev)
        np.testing.assert_array_equal(s.info["lower"], b0.lower)
        np.testing.assert_array_equal(s.info["upper"], b0.upper)
    s = states[2]
    M, h = jax.jit(jax.vmap(env.mass_and_bias))(s.pipeline_state.qpos, s.pipeline_state.qvel)
    tau = np.float32(w.torque_box_margin) * np.asarray(env.tau_max, np.float32)
    lo_c, hi_c = torque.torque_acc_box_conservative(M, h, tau, env.limits.a_max)
    scale = np.asarray(states[3].metrics["torque_box_scale"])  # the box of the step from s
    np.testing.assert_allclose(scale, torque.box_scale(M, h, tau, env.limits.a_max), rtol=1e-5)
    np.testing.assert_allclose(hi_c, np.clip(scale, 0, 1)[:, None] * env.limits.a_max[None], rtol=1e-5)
    np.testing.assert_array_equal(lo_c, -hi_c)


@pytest.mark.parametrize("method", ["none", "viability"])
def test_non_finite_actions_never_reach_the_simulator(env, method):
    """NaN/inf commands are replaced, whole, by braking (projected into the bounds) and counted."""
    w = SafetyWrapper(env, method)
    bad_actions = jnp.array(
        [[jnp.nan, 0.0, 0.0], [0.5, jnp.inf, -0.5], [-jnp.inf, jnp.nan, 1.0], [0.1, 0.2, 0.3]], jnp.float32
    )[:, : env.n]

    @jax.jit
    def run(key):
        s = w.reset(key)
        s = w.step(s, jnp.full((env.n,), 1.0, jnp.float32))  # get moving

        def body(s, a):
            s = w.step(s, a)
            return s, (
                s.metrics["nonfinite_action"],
                s.metrics["intervention"],
                s.pipeline_state.qpos,
                s.pipeline_state.qvel,
                s.info["a_safe"],
                s.metrics["count/position"],
            )

        return jax.lax.scan(body, s, jnp.tile(bad_actions, (20, 1)))

    _, (flag, interv, qs, vs, a_safe, count_pos) = run(jax.random.PRNGKey(3))
    flag = np.asarray(flag)
    np.testing.assert_array_equal(flag, np.tile([1.0, 1.0, 1.0, 0.0], 20))
    for x in (interv, qs, vs, a_safe):
        assert np.all(np.isfinite(np.asarray(x)))
    # a replaced step is a braking command inside the acceleration limits
    assert np.all(np.abs(np.asarray(a_safe)) <= np.asarray(env.limits.a_max, np.float32) + 1e-5)
    if method == "viability":
        assert np.sum(np.asarray(count_pos)) == 0
