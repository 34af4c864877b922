"""Training, evaluation and the main job: configs, checkpoints, violation tallies, sharding, the CLI."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.training import checkpoint, config, evaluate, tally


# ----------------------------------------------------------------------------- configs


def test_shipped_configs_load_and_validate():
    for path in sorted(config.CONFIG_DIR.glob("*.json")):
        cfg = config.load(path)
        assert config.from_dict(cfg.to_dict()) == cfg
    assert config.load("planar_reach_ppo").eval_episodes >= 10_000


@pytest.mark.parametrize(
    "bad, field",
    [
        ({"shield": "nope"}, "shield"),
        ({"env": "cartpole"}, "env"),
        ({"num_timesteps": 0}, "num_timesteps"),
        ({"ppo": {"num_envs": -4}}, "ppo.num_envs"),
        ({"ppo": {"learning_rate": -1.0}}, "ppo.learning_rate"),
        ({"colour": "red"}, "colour"),
        ({"ppo": {"num_envs": 3}}, "num_envs"),
        ({"episode_length": 201}, "action_repeat"),
        ({"algo": "sac"}, "algo"),
        ({"action_mode": "torque"}, "action_mode"),
        ({"ik_observation": "yes"}, "ik_observation"),
        ({"precision_reward": -1.0}, "precision_reward"),
        ({"apg": {"horizon_length": 0}}, "apg.horizon_length"),
        ({"apg": {"normalize_observations": 1}}, "apg.normalize_observations"),
        ({"apg": {"policy_hidden": []}}, "apg.policy_hidden"),
        ({"apg": {"horizon_length": 9, "action_repeat": 2}}, "apg.action_repeat"),
        ({"apg": {"shield_gradient": "smooth"}}, "apg.shield_gradient"),
    ],
)
def test_bad_config_raises_with_the_field(bad, field):
    d = config.load("tiny").to_dict()
    for section in ("ppo", "apg"):
        d[section] = dict(d[section], **bad.pop(section, {}))
    d.update(bad)
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        config.from_dict(d)


def test_override_replaces_fields_and_section_fields_and_validates():
    cfg = config.load("tiny")
    new = cfg.override(num_timesteps=1234, shield=None, ppo={"num_evals": 3})
    assert (new.num_timesteps, new.shield, new.ppo.num_evals) == (1234, cfg.shield, 3)
    assert new.ppo.num_envs == cfg.ppo.num_envs and new.apg == cfg.apg
    with pytest.raises(ValueError, match="ppo.num_envs"):
        cfg.override(ppo={"num_envs": -4})
    with pytest.raises(ValueError, match="shield"):
        cfg.override(shield="nope")
    with pytest.raises(ValueError, match="colour"):
        cfg.override(colour="red")


def test_config_choices_match_the_library():
    """The config module lists the choices without importing MuJoCo; they must stay the library's."""
    from jaxlimits.envs.actions import ACTION_MODES
    from jaxlimits.envs.joint_shield import METHODS
    from jaxlimits.envs.reach import ACTIONS
    from jaxlimits.envs.safety import SHIELD_GRADIENTS

    assert config.SHIELD_GRADIENTS == SHIELD_GRADIENTS and config.ARM_ACTION_MODES == ACTION_MODES
    assert config.SERVO_ACTION_MODES == ACTIONS and set(config.SERVO_SHIELDS) == set(METHODS)
    assert set(config.ROBOT_ENVS) <= set(config.ENVS) and "planar_robot_wall" in config.CONTACT_ENVS
    for modes in config.ROBOT_ACTION_MODES.values():  # Reach's own, or a parametrisation over its accelerations
        assert set(modes) <= set(ACTIONS) | set(ACTION_MODES), modes


def test_the_planar_arm_trains_under_the_one_shield_through_its_config():
    """``planar_robot_reach``: the planar arm as a robot (``Reach(action="acceleration")``) inside
    ``JointLimitShield``, velocity actions tracked through it as over ``SafetyWrapper``; the config refuses the
    servo env's actions for it (and the arm's task-space ones, which need ``ArmReach``)."""
    from jaxlimits.envs import JointLimitShield
    from jaxlimits.envs.actions import VelocityActions
    from jaxlimits.envs.reach import Reach
    from jaxlimits.envs.violation_metrics import ViolationMetrics
    from jaxlimits.training.brax_ppo import env_from_config

    cfg = config.load("planar_robot_reach_ppo")
    assert cfg.override(env="planar_reach") == config.load("planar_reach_ppo")  # the same run otherwise
    env = env_from_config(cfg)
    assert isinstance(env, ViolationMetrics) and isinstance(env.env, VelocityActions)
    shield = env.env.env
    assert isinstance(shield, JointLimitShield) and shield.method == "viability"
    assert isinstance(shield.env, Reach) and shield.env.action_mode == "acceleration"
    np.testing.assert_allclose(shield.env._accelerations.scale, shield.robot.limits.a_max)
    assert isinstance(env_from_config(cfg.override(action_mode="acceleration")).env, JointLimitShield)
    for bad in ("servo_offset", "task_space"):
        with pytest.raises(ValueError, match="config field 'action_mode' must be one of"):
            cfg.override(action_mode=bad)
    # it is the main job's reach unless --config or --env names another
    from jaxlimits.training import cli

    flags = dict(config=None, env=None, algo=None, steps=None, seed=None, episodes=None)
    assert cli.main_reach_config(argparse.Namespace(**flags)) == cfg
    assert cli.main_reach_config(argparse.Namespace(**{**flags, "env": "planar_reach"})) == config.load(
        "planar_reach_ppo"
    )
    assert cli.main_reach_config(argparse.Namespace(**{**flags, "config": "tiny"})) == config.load("tiny")


def test_the_unshielded_contact_task_measures_its_strikes():
    """``planar_robot_wall`` under ``shield="none"``: its strikes measured against the cap's bound, the cap not
    enforced (as the campaign's none rows), so a trained run's unshielded rows count them; capped with ``impact``."""
    from jaxlimits.envs import JointLimitShield
    from jaxlimits.training.brax_ppo import env_from_config

    cfg = config.load("planar_robot_wall_ppo")

    def shield_of(cfg):
        env = env_from_config(cfg)
        while not isinstance(env, JointLimitShield):
            env = env.env
        return env

    assert cfg.impact
    capped, unshielded = shield_of(cfg), shield_of(cfg.override(shield="none", impact=False))
    assert capped.impact.enforce and "impact" in capped.violations
    assert unshielded.method == "none" and not unshielded.impact.enforce and "impact" in unshielded.violations
    assert shield_of(cfg.override(impact=False)).impact is None  # a shield without the cap: none


def test_apg_config_selects_the_shield_gradient():
    from jaxlimits.envs import SafetyWrapper
    from jaxlimits.training.brax_ppo import env_from_config

    def shield_gradient(cfg):
        env = env_from_config(cfg)
        while not isinstance(env, SafetyWrapper):
            env = env.env
        return env.gradient

    cfg = config.load("planar_reach_apg")
    straight = cfg.override(apg={"shield_gradient": "straight_through"})
    assert shield_gradient(cfg) == "exact"
    assert shield_gradient(straight) == "straight_through"
    assert shield_gradient(straight.override(algo="ppo")) == "exact"  # PPO does not differentiate the env


def test_a_final_evaluation_reuses_the_runs_evaluator_only_for_its_config_and_episodes(monkeypatch):
    """``brax_ppo.training_evaluator`` hands back the last PPO run's evaluator only for the same config and
    episode count; ``evaluate.evaluate`` refuses an evaluator built for other episodes (naming both)."""
    import types

    from jaxlimits.training import brax_ppo, evaluate

    cfg = config.load("tiny")
    built = types.SimpleNamespace(episodes=8, episode_length=cfg.episode_length, action_repeat=cfg.action_repeat)
    monkeypatch.setattr(brax_ppo, "_LAST_EVALUATOR", [(brax_ppo._evaluator_key(cfg, 8), built)])
    assert brax_ppo.training_evaluator(cfg, 8) is built
    assert brax_ppo.training_evaluator(cfg, 16) is None
    assert brax_ppo.training_evaluator(cfg.override(seed=1), 8) is None
    with pytest.raises(ValueError, match=r"built for .* \(8, 20, 2\), asked for \(16, 20, 2\)"):
        evaluate.evaluate(None, None, None, episodes=16, episode_length=20, action_repeat=2, evaluator=built)


# ----------------------------------------------------------------------------- checkpoints


def test_checkpoint_roundtrip_and_refusals(tmp_path):
    params = {"w": np.arange(6, dtype=np.float32).reshape(2, 3), "b": (np.ones(3), np.float32(2.5))}
    path = checkpoint.save(tmp_path / "p.msgpack", params, meta={"env": "planar_reach"})
    back = checkpoint.load(path, jax.tree.map(np.zeros_like, params))
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(back)):
        np.testing.assert_array_equal(a, b)
    assert checkpoint.read_meta(path) == {"env": "planar_reach"}
    with pytest.raises(ValueError, match="does not match"):
        checkpoint.load(path, {"other": np.zeros(2)})
    (tmp_path / "junk.msgpack").write_bytes(b"\x80\x04not msgpack at all")
    with pytest.raises(ValueError):
        checkpoint.load(tmp_path / "junk.msgpack", params)
    assert b"pickle" not in path.read_bytes()


# ----------------------------------------------------------------------------- tallies


@pytest.fixture(scope="module")
def planar():
    from jaxlimits.envs import make_planar_reach

    return make_planar_reach(torque_samples=0)


@pytest.mark.parametrize("action_repeat", [1, 2])
def test_tally_counts_every_env_step(planar, action_repeat):
    """The host tally equals the violations summed over every env step, batch and action repeat."""
    from jaxlimits.envs import SafetyWrapper

    counts = tally.Tally()
    env = tally.wrap_for_training(counts)(
        SafetyWrapper(planar, method="none"), episode_length=30 * action_repeat, action_repeat=action_repeat
    )
    batch, steps = 4, 80  # auto-resets after 30 steps: totals run across episodes
    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))

    @jax.jit
    def run(state, key):
        def body(s, k):
            s = env.step(s, jnp.full((batch, planar.action_size), 1.5) * jnp.sign(jax.random.normal(k, (batch, 1))))
            return s, s.info["tally"]

        return jax.lax.scan(body, state, jax.random.split(key, steps))

    state, per_step = run(state, jax.random.PRNGKey(1))
    jax.effects_barrier()
    assert counts.env_steps == batch * steps * action_repeat
    final = state.info["tally"]
    for k in ("position", "velocity"):
        expect = int(np.sum(np.asarray(final[f"count/{k}"])))
        assert counts.counts[f"count/{k}"] == expect
        assert counts.maxes[f"violation/{k}"] == pytest.approx(float(np.max(final[f"violation/{k}"])))
    assert counts.counts["count/velocity"] > 0  # the unshielded full-acceleration policy does violate


def test_tally_refuses_a_domain_randomisation_it_could_not_count(planar):
    """Brax's DomainRandomizationVmapWrapper steps the innermost env past the tally's StepTally: refused, not a
    silent zero."""
    from jaxlimits.envs import SafetyWrapper

    with pytest.raises(ValueError, match="randomization_fn.*shield/"):
        tally.wrap_for_training(tally.Tally())(SafetyWrapper(planar, method="none"), randomization_fn=lambda s: (s, s))


# ----------------------------------------------------------------------------- evaluation


def test_scripted_evaluation_counts_and_shield(planar):
    from jaxlimits.envs import SafetyWrapper

    rows = {}
    for shield in ("none", "viability"):
        env = SafetyWrapper(planar, method=shield)
        pol = evaluate.scripted_policy("toward_limit", env.action_size)
        rows[shield] = evaluate.evaluate(env, pol, None, episodes=16, episode_length=150, seed=3)
    assert rows["none"]["violations/position"] > 0 and rows["none"]["max_violation/position"] > 0.05
    assert rows["viability"]["violations/position"] == 0 and rows["viability"]["violations/velocity"] == 0
    assert rows["viability"]["env_steps"] == 16 * 150
    table = evaluate.format_table(rows)
    assert "viability" in table and "none" in table
    with pytest.raises(ValueError, match="kind"):
        evaluate.scripted_policy("sideways", 3)


def test_the_evaluator_batches_its_episodes_step_once(planar):
    """Under ``vmap`` a ``lax.scan`` carry that enters unbatched and leaves batched makes JAX batch the scan's body
    again; the evaluator's carries (state, sums, held action) all enter batched, so the env step, with its shield,
    is batched once per trace. Counted with a ``custom_vmap`` identity in the step, whose rule runs once per
    batching of the body (the evaluator before this fix: twice). Traced, not compiled."""
    from jaxlimits.envs import SafetyWrapper

    batchings = []

    @jax.custom_batching.custom_vmap
    def mark(a):
        return a

    @mark.def_vmap
    def _(axis_size, in_batched, a):
        batchings.append(axis_size)
        return a, in_batched[0]

    class MarkedStep:
        def __init__(self, env):
            self.env, self.action_size = env, env.action_size

        def reset(self, key):
            return self.env.reset(key)

        def step(self, state, action):
            return self.env.step(state, mark(action))

    env = MarkedStep(SafetyWrapper(planar, method="viability"))
    for repeat in (1, 2):
        batchings.clear()
        ev = evaluate.Evaluator(
            env, evaluate.scripted_policy("random", env.action_size), episodes=3, episode_length=4, action_repeat=repeat
        )
        jax.make_jaxpr(ev.program)(None, jax.random.key_data(jax.random.split(jax.random.PRNGKey(0), 3)))
        assert batchings == [3], (repeat, batchings)


SHARDING_SCRIPT = textwrap.dedent("""
    import json, jax, numpy as np
    from jaxlimits.envs import make_planar_reach, SafetyWrapper
    from jaxlimits.training import evaluate
    assert len(jax.devices()) == 2, jax.devices()
    env = SafetyWrapper(make_planar_reach(torque_samples=0), method="none")
    pol = evaluate.scripted_policy("bang_bang", env.action_size)
    out = {}
    for n in (1, 2):
        per = evaluate.rollout_episodes(env, pol, None, episodes=5, episode_length=40, action_repeat=2, seed=7,
                                        devices=jax.devices()[:n])
        out[n] = {k: np.asarray(v).tolist() for k, v in per.items()}
    print("JSON" + json.dumps(out))
""")


def test_sharded_evaluation_equals_one_device():
    """5 episodes (padded to 6) over 2 simulated host devices give the results of 1 device."""
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2").strip()
    proc = subprocess.run([sys.executable, "-c", SHARDING_SCRIPT], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.split("JSON", 1)[1])
    one, two = out["1"], out["2"]
    assert set(one) == set(two)
    for k in one:
        np.testing.assert_allclose(np.asarray(one[k]), np.asarray(two[k]), rtol=1e-6, atol=1e-6, err_msg=k)
    assert sum(one["count/position"]) > 0  # the comparison covers violations, not only zeros


# ----------------------------------------------------------------------------- the CLI end to end


def _cli(*args, timeout=900):
    proc = subprocess.run(
        [sys.executable, "-m", "jaxlimits.training.cli", *args], capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    return proc


@pytest.fixture(scope="module")
def main_job(tmp_path_factory):
    """``jaxlimits main --task reach --config tiny --env planar_robot_reach`` (the main job's env: the planar arm
    under the one shield): its output folder and the completed process."""
    out = tmp_path_factory.mktemp("main_job") / "main"
    return out, _cli("main", "--task", "reach", "--config", "tiny", "--env", "planar_robot_reach", "--out", str(out))


def test_main_job_trains_and_evaluates_on_a_tiny_budget(main_job, monkeypatch):
    """``jaxlimits main --task reach`` (tiny config) trains both shields, evaluates, plots; the checkpoint reloads.
    (The contact task's half of the main job: tests/test_contact_task.py.)"""
    out, proc = main_job
    assert "| reach | viability |" in proc.stdout and "| reach | none |" in proc.stdout
    assert "contact" not in json.loads((out / "results.json").read_text())
    results = json.loads((out / "results.json").read_text())
    vi = results["shields"]["viability"]
    from jaxlimits.training import brax_ppo

    assert results["config"]["env"] == "planar_robot_reach"
    assert vi["training"]["env_steps"] == brax_ppo.total_env_steps(config.load("tiny")) >= 4000
    assert vi["training"]["violations/position"] == 0 and vi["training"]["violations/velocity"] == 0
    # tiny's eval_episodes equal its num_eval_envs: the final evaluation is the in-training evaluator's program
    # (a persistent-cache hit instead of a second MJX compile)
    tiny = config.load("tiny")
    assert vi["evaluation"]["episodes"] == tiny.eval_episodes == tiny.ppo.num_eval_envs
    assert vi["evaluation"]["violations/position"] == 0 and vi["evaluation"]["violations/velocity"] == 0
    ref = results["reference"]  # the scripted IK controller on the same episodes (velocity actions + IK observation)
    assert (
        ref["episodes"] == vi["evaluation"]["episodes"]
        and ref["violations/position"] == 0
        and ref["violations/velocity"] == 0
    )
    assert "| reach | reference: scripted IK, viability |" in proc.stdout
    png = (out / "training_curves.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    rows = [json.loads(x) for x in (out / "runs" / "viability" / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) >= 2 and rows[-1]["step"] >= 4000
    # notebook 06 shows this run (and checks its guarantees) as it shows `make demo`'s
    from conftest import NOTEBOOK_DIR, run_notebook

    run_notebook(NOTEBOOK_DIR / "06_training.ipynb", monkeypatch, JAXLIMITS_RESULTS=str(out))
    # the checkpoint reloads: the configuration it was trained with, finite parameters
    cfg, _, params = brax_ppo.load_policy(out / "runs" / "viability")
    assert cfg.shield == "viability" and cfg.env == "planar_robot_reach"
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(params))


@pytest.mark.extended  # one more process tracing the evaluation (~30 s); the reload itself: the test above
def test_evaluate_cli_reproduces_the_main_jobs_evaluation(main_job, tmp_path):
    """``jaxlimits evaluate --run`` on the main job's checkpoint reproduces the main job's evaluation."""
    from jaxlimits.training import brax_ppo

    out, _ = main_job
    vi = json.loads((out / "results.json").read_text())["shields"]["viability"]
    cfg, _, _ = brax_ppo.load_policy(out / "runs" / "viability")
    _cli(
        "evaluate",
        "--run",
        str(out / "runs" / "viability"),
        "--episodes",
        str(cfg.eval_episodes),
        "--seed",
        str(cfg.seed + 1),
        "--json",
        str(tmp_path / "eval.json"),
    )
    again = json.loads((tmp_path / "eval.json").read_text())["viability"]
    for k in ("return_mean", "success_rate", "violations/position", "violations/velocity"):
        assert again[k] == pytest.approx(vi["evaluation"][k], rel=1e-6), k


@pytest.mark.parametrize("algo", ["ppo", "sac"])
def test_sb3_runs_on_the_gymnasium_env(tmp_path, algo, monkeypatch):
    import tempfile

    from jaxlimits.training import sb3

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # SB3's default logger folder would land here
    model, metrics = sb3.train(
        "viability",
        total_timesteps=256,
        out=tmp_path,
        algo=algo,
        n_steps=128,
        batch_size=64,
        learning_starts=64,
        max_episode_steps=50,
    )
    assert metrics["env_steps"] >= 256 and metrics["algo"] == algo
    assert not list(scratch.glob("SB3-*"))  # no empty SB3-<timestamp> folder left in the temporary directory
    assert metrics["violations/position"] == 0 and metrics["violations/velocity"] == 0
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    for p in model.policy.parameters():
        p.data.zero_()
    sb3.load_policy_arrays(model, tmp_path / "policy.npz")
    for k, v in model.policy.state_dict().items():
        assert bool((v == before[k]).all()), k
