"""The Panda front reach (Isaac Lab's Reach-Franka distribution): starts, targets, errors, and that the
scripted IK reference reaches its targets inside the limits (so a learned policy can)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxlimits.envs.arm import ASSETS, PANDA_FRONT_BOX, ArmReach, make_panda_front_reach
from jaxlimits.training import brax_ppo, config, evaluate, experiment  # at import: they set XLA flags


@pytest.fixture(scope="module")
def env():
    return make_panda_front_reach(torque_samples=0)


def test_starts_scale_the_home_keyframe_and_targets_fill_the_box(env):
    states = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), 512))
    q = np.asarray(states.pipeline_state.qpos, np.float64)
    home = env.home_qpos
    lim = env.limits
    span = lim.q_max - lim.q_min
    lo, hi = lim.q_min + env.reset_margin * span, lim.q_max - env.reset_margin * span
    scaled_lo = np.minimum(0.5 * home, 1.5 * home)
    scaled_hi = np.maximum(0.5 * home, 1.5 * home)
    tol = 1e-6
    assert np.all(q >= np.maximum(scaled_lo, lo) - tol) and np.all(q <= np.minimum(scaled_hi, hi) + tol)
    moving = home != 0.0
    assert np.array_equal(q[:, ~moving], np.zeros((512, int((~moving).sum())))), "zero home joints stay at 0"
    # the scale is spread over its range, not a constant: each scaled joint covers most of it
    ratio = q[:, moving] / home[moving]
    assert np.all(ratio.min(0) < 0.6) and np.all(ratio.max(0) > 1.4)
    assert np.all(np.asarray(states.pipeline_state.qvel) == 0.0)
    target = np.asarray(states.info["target"])
    box_lo, box_hi = (np.asarray(c) for c in PANDA_FRONT_BOX)
    assert np.all(target >= box_lo - 1e-6) and np.all(target <= box_hi + 1e-6)
    assert np.all(target.max(0) - target.min(0) > 0.8 * (box_hi - box_lo))


def test_bad_start_options_raise():
    with pytest.raises(ValueError, match="start"):
        make_panda_front_reach(torque_samples=0, start="anywhere")
    with pytest.raises(ValueError, match="home_scale"):
        make_panda_front_reach(torque_samples=0, home_scale=(1.5, 0.5))
    with pytest.raises(ValueError, match="home_scale"):
        make_panda_front_reach(torque_samples=0, home_scale=(0.5, float("nan")))
    with pytest.raises(ValueError, match="keyframe named 'home'"):
        ArmReach(ASSETS / "planar3.xml", "ee", (0, 0, 0), (1, 1, 1), torque_samples=0, start="home")


def test_the_shipped_config_builds_it_and_the_ik_reference_reaches_inside_the_limits():
    """``panda_front_reach_ppo`` (the Panda's learned reach) through the evaluator: the scripted IK reference
    reaches nearly every target within the episode, with 0 position, velocity and torque violations."""
    cfg = config.load("panda_front_reach_ppo")
    env = brax_ppo.env_from_config(cfg)
    policy = evaluate.ik_reference_policy(env.action_size, env.limits.v_max)
    row = evaluate.evaluate(
        env, policy, None, episodes=16, episode_length=cfg.episode_length, action_repeat=cfg.action_repeat, seed=3
    )
    assert row["success_rate"] >= 14 / 16, row
    for k in ("position", "velocity", "torque"):
        assert row[f"violations/{k}"] == 0, (k, row)


def test_trains_on_a_tiny_budget_with_zero_violations(tmp_path):
    """The Panda reach's config end to end on a tiny budget (Brax PPO through the shield, reload, evaluate):
    every training and evaluation env-step counted, 0 position, velocity and torque violations."""
    cfg = config.load("tiny").override(env="panda_front_reach")
    result = experiment.train_and_evaluate(cfg, tmp_path / "run", show_progress=False)
    train, ev = result["training"], result["evaluation"]
    # the final evaluation reused the run's in-training evaluator and its trace (one, though Brax's trainer runs
    # under rank promotion "allow" and the suite under "raise"); a fresh one on the reloaded checkpoint gives the
    # same row
    evaluator = brax_ppo.training_evaluator(cfg, cfg.eval_episodes)
    assert evaluator is not None and evaluator.program._cache_size() == 1
    brax_ppo._LAST_EVALUATOR.clear()
    fresh = experiment.evaluate_run(tmp_path / "run", cfg.eval_episodes).row
    for k in ("return_mean", "success_rate", "final_distance_mean", "violations/position", "violations/velocity"):
        assert fresh[k] == ev[k], (k, fresh[k], ev[k])
    assert train["env_steps"] == brax_ppo.total_env_steps(cfg) >= 4000
    assert ev["episodes"] == cfg.eval_episodes and ev["env_steps"] == cfg.eval_episodes * cfg.episode_length
    for k in ("position", "velocity", "torque"):
        assert train[f"violations/{k}"] == 0 and ev[f"violations/{k}"] == 0, k
