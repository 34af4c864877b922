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
