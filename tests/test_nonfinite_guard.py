"""The non-finite-action guards (Brax ``NonFiniteActionGuard``, Gymnasium ``NonFiniteActionGuardWrapper``): a NaN/inf
action reaches neither the simulator nor the env's reward; a shield inside brakes on the replaced step."""

import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import brax.envs

from jaxlimits.envs import JointLimitShield, NonFiniteActionGuard
from jaxlimits.envs.gym import JointLimitShieldWrapper, NonFiniteActionGuardWrapper

BAD = (np.nan, np.inf, -np.inf, 1e12)


def _gym_pusher(shield: bool):
    env = gymnasium.make("Pusher-v5")
    if shield:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # the torque-derived a_max's quantile warning
            env = JointLimitShieldWrapper(env, v_max=2.0)
    return NonFiniteActionGuardWrapper(env)


def test_gym_guard_keeps_nan_out_of_the_reward_and_the_shield_brakes():
    env = _gym_pusher(shield=True)
    shield, d = env.env, env.unwrapped.data
    env.reset(seed=2)
    for _ in range(15):
        env.step(np.full(7, 2.0))
    speed = np.abs(d.qvel[shield.robot.dof_adr]).copy()
    assert speed.max() > 0.1  # moving: braking is visible
    for k in range(40):
        action = np.full(7, 2.0)
        action[k % 7] = BAD[k % 4]
        _, reward, _, _, info = env.step(action)
        assert np.isfinite(reward) and info["nonfinite_action"] and info["shield"]["nonfinite"]
        assert info["violation"]["position"] == info["violation"]["velocity"] == 0.0
        assert np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))
    assert env.replaced == 40 and shield.tally["nonfinite"] == 40
    # braked: -sign(v) a_max held for a step chatters about rest by at most one step's a_max T
    T = shield.robot.timestep * env.unwrapped.frame_skip
    assert np.all(np.abs(d.qvel[shield.robot.dof_adr]) <= shield.robot.limits.a_max * T * (1 + 1e-6))
    # a finite action afterwards is the env's again: not replaced, not braked
    _, reward, _, _, info = env.step(np.full(7, 0.5))
    assert not info["nonfinite_action"] and not info["shield"]["nonfinite"] and env.replaced == 40


def test_gym_guard_alone_passes_zeros_and_without_it_the_reward_is_nan():
    env = _gym_pusher(shield=False)
    env.reset(seed=3)
    _, reward, _, _, info = env.step(np.array([np.nan, 1, 1, 1, 1, 1, 1.0]))
    assert np.isfinite(reward) and info["nonfinite_action"]
    np.testing.assert_array_equal(env.unwrapped.data.ctrl, np.zeros(7))
    raw = gymnasium.make("Pusher-v5").unwrapped  # the env itself: Pusher's control cost uses the action
    raw.reset(seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # MuJoCo's bad-ctrl warning, Gymnasium's NaN-reward warning
        _, raw_reward, _, _, _ = raw.step(np.array([np.nan, 1, 1, 1, 1, 1, 1.0]))
    assert not np.isfinite(raw_reward)


def test_brax_guard_keeps_nan_out_of_the_reward_and_the_shield_brakes():
    base = brax.envs.get_environment("reacher", backend="mjx")
    env = NonFiniteActionGuard(JointLimitShield(base, v_max=4.0))
    step = jax.jit(env.step)
    st = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert float(st.metrics["nonfinite_action"]) == 0.0
    for _ in range(10):
        st = step(st, jnp.ones(env.action_size, jnp.float32))
    for k in range(12):
        a = np.ones(env.action_size, np.float32)
        a[k % env.action_size] = BAD[k % 4]
        st = step(st, jnp.asarray(a, jnp.float32))
        assert np.isfinite(float(st.reward))
        assert float(st.metrics["nonfinite_action"]) == 1.0 and float(st.metrics["shield/nonfinite"]) == 1.0
        assert float(st.info["violation"]["position"]) == float(st.info["violation"]["velocity"]) == 0.0
        assert np.all(np.isfinite(np.asarray(st.pipeline_state.qpos)))
    st = step(st, jnp.full(env.action_size, 0.5, jnp.float32))
    assert float(st.metrics["nonfinite_action"]) == 0.0 and float(st.metrics["shield/nonfinite"]) == 0.0
    # the same NaN action on the env itself (a fresh one: the shield took over base's physics call): NaN reward
    base = brax.envs.get_environment("reacher", backend="mjx")
    with jax.numpy_rank_promotion("allow"):  # Brax's own MJX pipeline broadcasts implicitly
        raw = jax.jit(base.step)(jax.jit(base.reset)(jax.random.PRNGKey(0)), jnp.full(base.action_size, jnp.nan))
    assert not np.isfinite(float(raw.reward))
