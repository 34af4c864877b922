"""Brax PPO with the shield inside the env, every violation counted, msgpack checkpoints.

``train(cfg, run_dir)`` trains ``brax.training.agents.ppo`` on ``make_env(cfg.env, cfg.shield)``
(the ``SafetyWrapper`` sits inside the env, so every physics step of training and of PPO's own
evaluations is shielded), wrapped with ``tally.wrap_for_training`` so that violations are counted
at every env step. It writes to ``run_dir``: ``config.json``, ``metrics.jsonl`` (one line per PPO
evaluation: step, wall time, evaluation return/distance/violations, the running violation totals
of training), ``params.msgpack`` (``checkpoint.save``) and ``summary.json``.

``load_policy(run_dir)`` rebuilds the networks from the stored config and returns
``(policy, params)`` for ``evaluate.evaluate``.
"""

from __future__ import annotations

import contextlib
import functools
import json
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from brax.training import acme
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as brax_ppo_train

from jaxlimits.training import checkpoint, evaluate, tally
from jaxlimits.training.config import CONTACT_ENVS, RunConfig, from_dict


def make_base_env(name: str, **kwargs):
    """The unshielded env (an ``ArmReach``; ``planar_wall``: a ``WallStrike``) for a config's ``env`` name
    (``kwargs`` go to its constructor)."""
    from jaxlimits.envs import make_panda_reach, make_planar_reach, make_planar_wall_strike

    makers = {
        "planar_reach": make_planar_reach,
        "panda_reach": make_panda_reach,
        "planar_wall": make_planar_wall_strike,
    }
    return makers[name](**kwargs)


def make_env(
    name: str,
    shield: str,
    action_mode: str = "acceleration",
    shield_gradient: str = "exact",
    impact: bool = False,
    **kwargs,
):
    """``SafetyWrapper(env(**kwargs), method=shield, gradient=shield_gradient, impact=impact)`` with the
    policy's actions meaning ``action_mode`` (``jaxlimits.envs.actions``): the env every algorithm
    and the evaluator see. ``impact``: the impact-aware speed cap (envs with contacts)."""
    from jaxlimits.envs import SafetyWrapper
    from jaxlimits.envs.actions import with_action_mode

    shielded = SafetyWrapper(
        make_base_env(name, **kwargs), method=shield, gradient=shield_gradient, impact=True if impact else None
    )
    return with_action_mode(shielded, action_mode)


def env_from_config(cfg: RunConfig):
    """``make_env`` with the config's env, shield, impact cap, action mode, observation and reward (and,
    for APG, the derivative of the shield its policy gradient goes through)."""
    shield_gradient = cfg.apg.shield_gradient if cfg.algo == "apg" else "exact"
    reach = {} if cfg.env in CONTACT_ENVS else {"ik_observation": cfg.ik_observation}
    return make_env(
        cfg.env,
        cfg.shield,
        cfg.action_mode,
        shield_gradient,
        impact=cfg.impact,
        precision_reward=cfg.precision_reward,
        **reach,
    )


def _networks(cfg: RunConfig, obs_size, action_size: int, preprocess_observations_fn=None):
    """PPO networks with the config's sizes (Brax's ``network_factory`` signature)."""
    if preprocess_observations_fn is None:
        preprocess_observations_fn = (
            running_statistics.normalize if cfg.ppo.normalize_observations else (lambda x, y: x)
        )
    return ppo_networks.make_ppo_networks(
        obs_size,
        action_size,
        preprocess_observations_fn=preprocess_observations_fn,
        policy_hidden_layer_sizes=tuple(cfg.ppo.policy_hidden),
        value_hidden_layer_sizes=tuple(cfg.ppo.value_hidden),
    )


def total_env_steps(cfg: RunConfig) -> int:
    """The env steps Brax PPO will train for: ``num_timesteps`` rounded up to whole training epochs.

    (``brax.training.agents.ppo.train``: ``num_evals - 1`` epochs of ``ceil(num_timesteps /
    ((num_evals - 1) * batch_size * unroll_length * num_minibatches * action_repeat))`` steps.)
    """
    p = cfg.ppo
    per_step = p.batch_size * p.unroll_length * p.num_minibatches * p.action_repeat
    epochs = max(p.num_evals - 1, 1)
    return -(-cfg.num_timesteps // (epochs * per_step)) * epochs * per_step


class _Progress:
    """Brax PPO's ``policy_params_fn``: evaluate the current policy, log a ``metrics.jsonl`` row, draw the bar.

    Called at step 0 and after every training epoch group (``num_evals`` times). The evaluation is
    ``evaluate.Evaluator`` (deterministic policy, ``eval_episodes_during_training`` episodes, the
    same shielded env), compiled once; its violations are counted in the row, apart from training's.
    """

    def __init__(self, cfg: RunConfig, run_dir: Path, counts: tally.Tally, env, show: bool):
        self.cfg, self.counts, self.env, self.show = cfg, counts, env, show
        self.file = (run_dir / "metrics.jsonl").open("w")
        self.t0 = time.perf_counter()
        self.rows = []
        self.evaluator = None

    def __call__(self, step, make_policy, params):
        if self.evaluator is None:
            policy = deterministic_policy(make_policy)
            self.evaluator = evaluate.Evaluator(
                self.env,
                policy,
                episodes=self.cfg.num_eval_envs,
                episode_length=self.cfg.episode_length,
                action_repeat=self.cfg.action_repeat,
            )
        per = self.evaluator(params, seed=10_000 + len(self.rows))
        ev = evaluate.summarize(per, self.cfg.episode_length)
        row = {"step": int(step), "wall_s": round(time.perf_counter() - self.t0, 2)}
        row.update({f"eval/{k}": v for k, v in ev.items()})
        row.update({f"train/{k}": v for k, v in self.counts.as_dict().items()})
        self.rows.append(row)
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
        if self.show:
            total = total_env_steps(self.cfg)
            frac = min(step / total, 1.0)
            bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
            viol = row["train/violations/position"] + row["train/violations/velocity"]
            print(
                f"[{self.cfg.shield:>9}] [{bar}] {step:>10,d}/{total:,d} steps "
                f"{row['wall_s']:7.1f} s | eval return {ev['return_mean']:8.2f} success {ev['success_rate']:.2f} | "
                f"training pos+vel violations {viol}",
                file=sys.stderr,
                flush=True,
            )

    def close(self):
        self.file.close()


def start_run(cfg: RunConfig, run_dir) -> Path:
    """Create the run folder and write its ``config.json`` (every algorithm's run folder starts so)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
    return run_dir


def finish_run(cfg: RunConfig, run_dir: Path, params, counts: tally.Tally, wall: float, rows: list) -> dict:
    """Save ``params.msgpack`` (the config as its metadata) and ``summary.json``; return the summary.

    ``rows`` are the run's ``metrics.jsonl`` rows; the last one is the summary's ``final_eval``.
    """
    checkpoint.save(run_dir / "params.msgpack", params, meta=cfg.to_dict())
    summary = {
        "config": cfg.to_dict(),
        "wall_s": wall,
        "training": counts.as_dict(),
        "env_steps_per_s": counts.env_steps / wall,
        "final_eval": rows[-1] if rows else {},
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


@contextlib.contextmanager
def brax_compat(*deprecated: str):
    """What brax 0.14.2's trainers need under the pinned versions: they call ``jax.device_put_replicated``
    (and APG ``optax.global_norm``: pass it in ``deprecated``), deprecated there (an error where warnings
    are errors, as in the tests), and their observation normaliser relies on rank promotion."""
    with warnings.catch_warnings(), jax.numpy_rank_promotion("allow"):
        for message in ("jax.device_put_replicated is deprecated", *deprecated):
            warnings.filterwarnings("ignore", message, DeprecationWarning)
        yield


def train(cfg: RunConfig, run_dir, show_progress: bool = True) -> dict:
    """Train and save; returns the summary (also written to ``run_dir/summary.json``)."""
    run_dir = start_run(cfg, run_dir)
    env = env_from_config(cfg)
    counts = tally.Tally()
    progress = _Progress(cfg, run_dir, counts, env, show_progress)
    p = cfg.ppo
    t0 = time.perf_counter()
    try:
        with brax_compat():
            _, params, _ = brax_ppo_train.train(
                environment=env,
                num_timesteps=cfg.num_timesteps,
                episode_length=cfg.episode_length,
                action_repeat=p.action_repeat,
                num_envs=p.num_envs,
                batch_size=p.batch_size,
                num_minibatches=p.num_minibatches,
                unroll_length=p.unroll_length,
                num_updates_per_batch=p.num_updates_per_batch,
                learning_rate=p.learning_rate,
                entropy_cost=p.entropy_cost,
                discounting=p.discounting,
                reward_scaling=p.reward_scaling,
                normalize_observations=p.normalize_observations,
                num_evals=p.num_evals,
                run_evals=False,
                seed=cfg.seed,
                policy_params_fn=progress,
                wrap_env_fn=tally.wrap_for_training(counts),
                network_factory=functools.partial(_networks, cfg),
            )
    finally:
        progress.close()
    return finish_run(cfg, run_dir, params, counts, time.perf_counter() - t0, progress.rows)


def load_policy(run_dir):
    """``(cfg, policy, params)`` from a run folder; ``policy(params, obs, key, t) -> action`` (deterministic)."""
    run_dir = Path(run_dir)
    cfg = from_dict(checkpoint.read_meta(run_dir / "params.msgpack"))
    env = env_from_config(cfg)
    nets = _networks(cfg, env.observation_size, env.action_size)
    key = jax.random.PRNGKey(0)
    obs_spec = acme.specs.Array((env.observation_size,), jnp.dtype("float32"))
    template = (running_statistics.init_state(obs_spec), nets.policy_network.init(key), nets.value_network.init(key))
    params = checkpoint.load(run_dir / "params.msgpack", template)
    return cfg, deterministic_policy(ppo_networks.make_inference_fn(nets)), params


def deterministic_policy(make_policy):
    """The evaluator's ``policy(params, obs, key, t) -> action`` from a Brax ``make_policy``
    (``make_inference_fn(networks)``), deterministic; shared by PPO and APG."""

    def policy(params, obs, key, t):
        del t
        return make_policy(params, deterministic=True)(obs, key[1])[0]

    return policy
