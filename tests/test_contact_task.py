"""The contact task (planar wall strike, issue 15): every strike measured (re-strikes in an episode and across
Brax's auto-resets too); the training tally's strike counts equal a direct count; the impact cap keeps scripted
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
    """Through Brax's training wrappers (episodes auto-reset, ``info`` kept): the host tally counts every
    strike, a direct count over the steps (a strike = a step in contact after one out of contact, or the
    episode's first step in contact), at least two per episode here (strike, pull back, strike again: the
    record re-arms off the wall), and every env-step; over-bound strikes and the worst excess equal the env's own
    per-strike metrics."""
    counts = tally.Tally()
    E, batch, episodes = 80, 8, 3
    env = tally.wrap_for_training(counts)(SafetyWrapper(wall, "viability"), episode_length=E, action_repeat=1)
    scale = jnp.linspace(0.3, 1.0, batch, dtype=jnp.float32)[:, None]
    toward = scale * jnp.asarray(_toward_wall(wall), jnp.float32)[None]

    @jax.jit
    def run(key):
        state = env.reset(jax.random.split(key, batch))

        def body(s, t):
            phase = t % E  # toward the wall, away from it, toward it again
            s = env.step(s, jnp.where((phase >= 30) & (phase < 40), -1.0, 1.0) * toward)
            m = s.metrics
            return s, (m["contact"], m["strike"], m["strike_ratio"])

        return jax.lax.scan(body, state, jnp.arange(E * episodes))

    with jax.numpy_rank_promotion("allow"):
        _, (contact, strike, ratio) = run(jax.random.PRNGKey(0))
    jax.effects_barrier()
    contact = np.asarray(contact).reshape(episodes, E, batch)
    before = np.concatenate([np.zeros((episodes, 1, batch)), contact[:, :-1]], axis=1)
    onsets = (contact > 0) & (before == 0)
    # each episode: strike, pull back, strike again (the slowest strikes bounce once more: 3-4 onsets)
    assert np.all(onsets.sum(axis=1) >= 2), onsets.sum(axis=1)
    assert counts.env_steps == E * episodes * batch
    assert counts.counts["strike"] == int(onsets.sum()) == int(np.asarray(strike).sum())
    ratio = np.asarray(ratio)
    over = ratio > 1.0  # the ratio is reported once per strike, in the step its window closes
    assert counts.counts["count/impact"] == int(over.sum()) > 0  # uncapped full-speed strikes exceed the bound
    assert counts.maxes["violation/impact"] == pytest.approx(float(ratio.max()) - 1.0, rel=1e-5)


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
    """The main job's contact task on the tiny config, one variant (the job trains both; the uncapped one here:
    one MJX training compile less in the suite): a row in the one table, the training tally over every
    env-step, the evaluation's strikes counted, the contact job's own folder. The capped variant's env is the
    same with the cap wired in (checked)."""
    from jaxlimits.training import brax_ppo, contact_job, main_job

    cfg = config.load("tiny_wall")
    capped = brax_ppo.env_from_config(cfg)
    while not hasattr(capped, "impact"):
        capped = capped.env
    assert capped.impact is not None and capped.name == "viability+impact"
    results = main_job.run(tmp_path, None, show_progress=False, contact_cfg=cfg, contact_variants=("viability",))
    assert results.keys() == {"contact", "wall_s"}
    r = results["contact"]["variants"]["viability"]
    assert r["training"]["env_steps"] == brax_ppo.total_env_steps(cfg)
    assert r["evaluation"]["episodes"] == cfg.eval_episodes
    assert 0.0 <= r["evaluation"]["success_rate"] <= 1.0
    # every episode that struck counted at least one strike (re-strikes count too)
    assert r["evaluation"]["strikes"] >= round(r["evaluation"]["success_rate"] * cfg.eval_episodes)
    table = (tmp_path / "results.md").read_text()
    assert "| contact | viability |" in table and "viability+impact" not in table and "| reach |" not in table
    assert (tmp_path / "contact" / "results.md").read_text() == table
    assert json.loads((tmp_path / "contact" / "results.json").read_text())["variants"].keys() == {"viability"}
    for png in (tmp_path / "contact_curves.png", tmp_path / "contact" / "training_curves.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(ValueError, match="variants"):
        contact_job.run(tmp_path, cfg, variants=("bogus",))
    with pytest.raises(ValueError, match="contacts"):
        contact_job.run(tmp_path, config.load("tiny"))
    with pytest.raises(ValueError, match="at least one task"):
        main_job.run(tmp_path, None)


def test_one_table_for_every_task():
    """``experiment.format_table``: a row per run of every task, strikes only where there are strikes."""
    from jaxlimits.training import experiment

    def row(strikes, over):
        counts = {f"violations/{k}": 0 for k in ("position", "velocity", "impact")}
        counts.update({f"max_violation/{k}": 0.0 for k in ("position", "velocity", "impact")})
        counts.update({"env_steps": 1000, "strikes": strikes, "violations/impact": over})
        evaluation = {
            **counts,
            "episodes": 10,
            "success_rate": 1.0,
            "return_mean": 2.0,
            "max_strike_ratio": 1.5 if over else 0.5,
            "intervention_mean": 0.1,
        }
        return {
            "training": counts,
            "training_wall_s": 1.0,
            "training_env_steps_per_s": 1000.0,
            "evaluation": evaluation,
        }

    table = experiment.format_table(
        {
            "reach": {"runs": {"viability": row(0, 0)}, "reference": row(0, 0)["evaluation"]},
            "contact": {"runs": {"viability+impact": row(7, 0), "viability": row(9, 9)}},
        }
    )
    lines = table.splitlines()
    assert len(lines) == 2 + 4 and all(line.count("|") == 13 for line in lines)
    assert lines[2].startswith("| reach | viability |") and "| – |" in lines[2]
    assert lines[3].startswith("| reach | reference: scripted IK, viability |")
    assert lines[4].startswith("| contact | viability+impact |") and "| 7: 0 (0) |" in lines[4]
    assert "| 9: 9 (0) |" in lines[5] and "| 10 | 1.000 |" in lines[5]
