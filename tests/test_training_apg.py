"""Brax APG end to end through the shield (its own file so that pytest-xdist runs it next to test_training.py).

About 2 min, mostly compilation (the reverse pass through MJX); the shield's derivative itself is
checked against finite differences in tests/test_envs_actions.py.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits.training import config


def test_apg_trains_through_the_shield_and_reloads(tmp_path):
    """Brax APG (gradients through MJX and the shield) on a tiny budget: counted, zero violations, reloadable."""
    from jaxlimits.training import algos, brax_apg

    cfg = config.load("planar_reach_apg").override(
        num_timesteps=640,
        episode_length=20,
        eval_episodes=8,
        # two evaluations (one training epoch): a second epoch compiles the same program again (host callbacks keep
        # it out of the persistent cache), ~15 s that test nothing more
        apg={"num_envs": 8, "horizon_length": 8, "num_evals": 2, "num_eval_envs": 8, "policy_hidden": [16]},
    )
    summary = algos.train(cfg, tmp_path / "apg", show_progress=False)
    t = summary["training"]
    assert t["env_steps"] >= brax_apg.policy_updates(cfg) * 8 * 8
    assert t["violations/position"] == 0 and t["violations/velocity"] == 0 and t["nonfinite_actions"] == 0
    rows = [json.loads(x) for x in (tmp_path / "apg" / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and np.isfinite(rows[-1]["eval/episode_reward"])
    assert summary["final_eval"] == rows[-1]
    cfg2, policy, params = algos.load_policy(tmp_path / "apg")
    assert cfg2 == cfg and all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(params))
    obs = jnp.zeros((brax_apg.env_from_config(cfg2).observation_size,), jnp.float32)
    action = policy(params, obs, jax.random.split(jax.random.PRNGKey(0)), 0)
    assert action.shape == (3,) and np.all(np.abs(np.asarray(action)) <= 1.0)
