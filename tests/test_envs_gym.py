"""Gymnasium front: registered ids with shield=, check_env (Gymnasium and SB3), info contents, render."""

from __future__ import annotations

import warnings

import gymnasium
import numpy as np
import pytest

import jaxlimits.envs.gym as jgym
from jaxlimits.envs.arm import VIOLATION_KEYS


@pytest.fixture(scope="module")
def env():
    e = gymnasium.make("jaxlimits/PlanarReach-v0", shield="viability", render_mode="rgb_array")
    yield e
    e.close()


def test_ids_are_registered():
    assert "jaxlimits/PandaReach-v0" in gymnasium.registry
    assert "jaxlimits/PlanarReach-v0" in gymnasium.registry
    with pytest.raises(ValueError, match="method"):
        gymnasium.make("jaxlimits/PlanarReach-v0", shield="magic")


def test_gymnasium_check_env(env):
    from gymnasium.utils.env_checker import check_env

    check_env(env.unwrapped, skip_render_check=False)


def test_sb3_check_env(env):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # SB3 imports
        from stable_baselines3.common.env_checker import check_env
    check_env(env.unwrapped, warn=True)


def test_info_and_truncation(env):
    obs, info = env.reset(seed=3)
    assert set(info["violation"]) == set(VIOLATION_KEYS)
    push = np.ones(env.action_space.shape, np.float32)
    for t in range(500):
        obs, r, terminated, truncated, info = env.step(push)
        assert not terminated
        assert set(info["violation"]) == set(VIOLATION_KEYS)
        assert all(isinstance(v, float) for v in info["violation"].values())
        assert info["violation"]["position"] == 0.0 and info["violation"]["velocity"] == 0.0
        lim = env.unwrapped._wrapped.limits
        assert np.all(info["qpos"] <= lim.q_max) and info["qpos"].shape == (3,) and info["qvel"].shape == (3,)
        if truncated:
            break
    assert truncated and t == 499  # TimeLimit from the registration
    frame = env.render()
    assert frame.shape == (240, 240, 3) and frame.dtype == np.uint8 and frame.std() > 0


def test_vector_env_shares_the_compiled_step_and_autoresets():
    venv = jgym.ArmVectorEnv(1, arm="planar", shield="viability", max_episode_steps=3)
    obs, info = venv.reset(seed=0)
    assert obs.shape == (1, venv.single_observation_space.shape[0])
    for t in range(3):
        obs, r, term, trunc, info = venv.step(np.zeros((1, 3), np.float32))
    assert trunc.all() and not term.any() and "final_obs" in info
    assert set(info["violation"]) == set(VIOLATION_KEYS) and info["qpos"].shape == (1, 3)
    venv.close()


# ---- vector API (2 envs: one more compilation of the planar step, shared by the tests below) ---------
@pytest.fixture(scope="module")
def venv():
    v = jgym.ArmVectorEnv(2, arm="planar", shield="viability", max_episode_steps=3)
    yield v
    v.close()


def test_vector_env_reset_step_shapes_and_seeding(venv):
    obs, info = venv.reset(seed=7)
    obs_b, _ = venv.reset(seed=7)
    np.testing.assert_array_equal(obs, obs_b)
    assert obs.shape == (2, venv.single_observation_space.shape[0]) and obs.dtype == np.float32
    assert venv.observation_space.contains(obs)
    assert set(info["violation"]) == set(VIOLATION_KEYS)
    assert all(v.shape == (2,) and not v.any() for v in info["violation"].values())
    assert info["qpos"].shape == (2, 3) and info["qvel"].shape == (2, 3)
    actions = venv.action_space.sample()
    assert actions.shape == (2, 3)
    obs, r, term, trunc, info = venv.step(actions)
    assert obs.shape == (2, 9 + 6) and r.shape == (2,) and term.shape == (2,) and trunc.shape == (2,)
    assert term.dtype == bool and trunc.dtype == bool and not term.any() and not trunc.any()
    assert "final_obs" not in info and "final_info" not in info
    assert set(info["violation"]) == set(VIOLATION_KEYS) and all(v.shape == (2,) for v in info["violation"].values())
    assert info["intervention"].shape == (2,) and info["accel_error"].shape == (2,)


def test_vector_env_autoreset_same_step(venv):
    obs0, _ = venv.reset(seed=1)
    push = np.ones((2, 3), np.float32)
    for t in range(3):
        obs, r, term, trunc, info = venv.step(push)
        if t < 2:
            assert not trunc.any() and "final_obs" not in info
            last_obs = obs
    assert trunc.all() and not term.any()
    # Gymnasium's SAME_STEP convention: final_obs (object array), final_info, masks; obs is the fresh state's
    assert info["_final_obs"].all() and info["_final_info"].all()
    assert info["final_obs"].dtype == object and info["final_obs"][0].shape == obs0.shape[1:]
    for i in range(2):
        assert not np.array_equal(info["final_obs"][i], obs[i])
        assert not np.array_equal(info["final_obs"][i], last_obs[i])
    assert set(info["final_info"]["violation"]) == set(VIOLATION_KEYS)
    np.testing.assert_allclose(np.cos(info["final_info"]["qpos"]), np.stack(info["final_obs"])[:, :3], rtol=1e-6)
    np.testing.assert_allclose(np.cos(info["qpos"]), obs[:, :3], rtol=1e-6)  # top-level info: the fresh state
    np.testing.assert_array_equal(info["qvel"], 0.0)
    assert all(not v.any() for v in info["violation"].values())
    # the episode counter restarted: three more steps to the next truncation
    for t in range(3):
        obs, r, term, trunc, info = venv.step(push)
        assert trunc.all() == (t == 2)


def test_make_vec(venv):
    v = gymnasium.make_vec("jaxlimits/PlanarReach-v0", num_envs=2, shield="viability")
    assert isinstance(v.unwrapped, jgym.ArmVectorEnv) and v.num_envs == 2
    assert v.unwrapped.max_episode_steps == 500  # from the registration
    assert v.unwrapped._step_fn is venv._step_fn  # one compiled step per (arm, shield)
    obs, _ = v.reset(seed=0)
    obs, r, term, trunc, info = v.step(np.zeros((2, 3), np.float32))
    assert obs.shape == (2, 15) and set(info["violation"]) == set(VIOLATION_KEYS)
    v.close()
    sync = gymnasium.make_vec("jaxlimits/PlanarReach-v0", num_envs=2, vectorization_mode="sync", shield="viability")
    obs, _ = sync.reset(seed=0)
    obs, r, term, trunc, info = sync.step(np.zeros((2, 3), np.float32))
    assert obs.shape == (2, 15) and info["violation"]["position"].shape == (2,)
    sync.close()


def test_velocity_actions_and_ik_observation_through_gymnasium():
    """The Brax configs' task options reach the Gymnasium front: spaces follow them, steps obey them."""
    env = gymnasium.make(
        "jaxlimits/PlanarReach-v0",
        shield="viability",
        action_mode="velocity",
        ik_observation=True,
        precision_reward=1.0,
        max_episode_steps=20,
    )
    n = 3
    assert env.observation_space.shape == (4 * n + 6,) and env.action_space.shape == (n,)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(np.ones(n, np.float32))
        assert env.observation_space.contains(obs) and np.isfinite(reward)
        assert all(info["violation"][k] == 0.0 for k in ("position", "velocity", "acceleration", "torque"))
    # velocity actions: the joints speed up toward +v_max (as hard as the shield allows)
    assert np.all(info["qvel"] > 0)
    with pytest.raises(ValueError, match="action mode"):
        jgym.ArmEnv(action_mode="torque")
    env.close()
