"""The contact task (planar wall strike, issue 15): every strike measured once per episode, across Brax's
auto-resets too; the training tally's strike counts equal a direct count; the impact cap keeps scripted
strikes within the bound; bad configs are eager errors; the contact job runs on a tiny budget."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.envs.safety import SafetyWrapper
from jaxlimits.envs.wall_strike import make_planar_wall_strike, strike_experiment
from jaxlimits.training import config, tally


@pytest.fixture(scope="module")
def wall():
    return make_planar_wall_strike(torque_samples=2000)


def _toward_wall(env):
    """A joint direction ``(n,)`` moving the end effector along the wall normal at the home posture,
    scaled to ``max |x| = 1`` (an acceleration action)."""
    J = np.asarray(env.ee_jacobian(jnp.asarray(env.home, jnp.float32)))
    dq = np.linalg.pinv(J) @ env.normal
    return dq / np.max(np.abs(dq))


def test_tally_counts_every_strike_across_auto_resets(wall):
    """Through Brax's training wrappers (episodes auto-reset, ``info`` kept): the host tally's strikes and
    over-bound strikes equal a direct count over the episodes (struck = the ball penetrated the wall in
    some step of the episode; over = the episode's measured contact torque ratio > 1), and there is more
    than one strike per env (the record restarts at every episode)."""
    counts = tally.Tally()
    E, batch, episodes = 60, 8, 3
    env = tally.wrap_for_training(counts)(SafetyWrapper(wall, "viability"), episode_length=E, action_repeat=1)
    scale = jnp.linspace(0.3, 1.0, batch, dtype=jnp.float32)[:, None]
    action = scale * jnp.asarray(_toward_wall(wall), jnp.float32)[None]

    @jax.jit
    def run(key):
        state = env.reset(jax.random.split(key, batch))

        def body(s, _):
            s = env.step(s, action)
            m = s.metrics
            return s, (m["contact"], m["impact/tau_contact"])

        return jax.lax.scan(body, state, None, length=E * episodes)

    with jax.numpy_rank_promotion("allow"):
        _, (contact, ratio) = run(jax.random.PRNGKey(0))
    jax.effects_barrier()
    contact = np.asarray(contact).reshape(episodes, E, batch)
    ratio = np.asarray(ratio).reshape(episodes, E, batch)
    struck = contact.max(axis=1) > 0  # (episodes, batch)
    over = struck & (ratio[:, -1] > 1.0)  # the record holds the episode's strike until the next reset
    assert counts.env_steps == E * episodes * batch
    assert counts.counts["strike"] == int(struck.sum()) > batch
    assert counts.counts["count/impact"] == int(over.sum()) > 0  # uncapped full-speed strikes exceed the bound
    assert counts.maxes["violation/impact"] == pytest.approx(float(np.max(ratio[:, -1][over])) - 1.0, rel=1e-5)


def test_scripted_strikes_stay_within_the_bound_with_the_cap(wall):
    """The planar arm's scripted strikes (0.05-1 m/s commanded): with the cap every strike's contact torque
    is within the bound and no joint limit is violated; without it the fast ones exceed it."""
    shields = [SafetyWrapper(wall, "viability"), SafetyWrapper(wall, "viability", impact=True)]
    with jax.numpy_rank_promotion("allow"):
        r = strike_experiment(wall, shields, batch=64, steps=100, speed_range=(0.05, 1.0), seed=1)
    free, capped = r["viability"], r["viability+impact"]
    hit = capped["hit"] > 0
    assert hit.sum() > 32
    assert np.all(capped["tau_contact"][hit] <= 1.0), capped["tau_contact"][hit].max()
    assert np.all(capped["w"][hit] <= capped["cap"][hit] * 1.01 + 1e-3)
    for k in ("violation_position", "violation_velocity"):
        assert np.all(capped[k] == 0.0), (k, capped[k].max())
    assert np.any(free["tau_contact"][free["hit"] > 0] > 1.0)


def test_contact_configs_are_checked_eagerly():
    base = config.load("tiny_wall").to_dict()
    with pytest.raises(ValueError, match="'impact' needs an env with contacts"):
        config.from_dict({**base, "env": "planar_reach"})
    with pytest.raises(ValueError, match="reach options"):
        config.from_dict({**base, "ik_observation": True})
    with pytest.raises(ValueError, match="'impact' must be true or false"):
        config.from_dict({**base, "impact": "yes"})


def test_contact_job_trains_and_counts_strikes_on_a_tiny_budget(tmp_path):
    """The contact job on the tiny config, one variant (the job trains both; the uncapped one here: one MJX
    training compile less in the suite): a row in the table, the training tally over every env-step, the
    evaluation's strikes counted. The capped variant's env is the same with the cap wired in (checked)."""
    from jaxlimits.training import brax_ppo, contact_job

    cfg = config.load("tiny_wall")
    capped = brax_ppo.env_from_config(cfg)
    while not hasattr(capped, "impact"):
        capped = capped.env
    assert capped.impact is not None and capped.name == "viability+impact"
    results = contact_job.run(tmp_path, cfg, show_progress=False, variants=("viability",))
    r = results["variants"]["viability"]
    assert r["training"]["env_steps"] == brax_ppo.total_env_steps(cfg)
    assert r["evaluation"]["episodes"] == cfg.eval_episodes
    assert r["evaluation"]["strikes"] <= cfg.eval_episodes
    assert 0.0 <= r["evaluation"]["success_rate"] <= 1.0
    table = (tmp_path / "results.md").read_text()
    assert "| viability |" in table and "| viability+impact |" not in table
    assert json.loads((tmp_path / "results.json").read_text())["variants"].keys() == {"viability"}
    with pytest.raises(ValueError, match="variants"):
        contact_job.run(tmp_path, cfg, variants=("bogus",))
    with pytest.raises(ValueError, match="contacts"):
        contact_job.run(tmp_path, config.load("tiny"))
