"""Brax APG (analytic policy gradients) with the shield inside the differentiated path.

``train(cfg, run_dir)`` runs ``brax.training.agents.apg``: every policy update differentiates the
mean reward of ``apg.horizon_length`` env steps through MJX *and through the shield*, so the
derivative of the projection (``jaxlimits.project_box``'s custom JVP: identity on joints the
bounds leave free, zero on clipped ones, the bounds' own derivative with respect to the state on
those) is what the policy learns from. The same ``SafetyWrapper`` env as PPO's, counted by
``tally.wrap_for_training`` at every env step (``jax.debug.callback`` runs on the forward pass
only, so differentiation does not double-count).

The run folder is the same as PPO's (``config.json``, ``metrics.jsonl``, ``params.msgpack``,
``summary.json``); ``metrics.jsonl`` has one row per APG evaluation with Brax's evaluation
figures (``eval/episode_reward``, ``eval/episode_distance``...) and the running training tally,
and ``summary.json``'s ``final_eval`` is the last of those rows (Brax's evaluator, deterministic
policy, ``num_eval_envs`` episodes).
"""

from __future__ import annotations

import functools
import json
import sys
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from brax.training import acme
    from brax.training.acme import running_statistics
    from brax.training.agents.apg import networks as apg_networks
    from brax.training.agents.apg import train as brax_apg_train

from jaxlimits.training import checkpoint, tally
from jaxlimits.training.brax_ppo import brax_compat, deterministic_policy, env_from_config, finish_run, start_run
from jaxlimits.training.config import RunConfig, from_dict


def _networks(cfg: RunConfig, obs_size, action_size: int, preprocess_observations_fn=None):
    """APG policy network with the config's sizes (Brax's ``network_factory`` signature)."""
    if preprocess_observations_fn is None:
        preprocess_observations_fn = (
            running_statistics.normalize if cfg.apg.normalize_observations else (lambda x, y: x)
        )
    return apg_networks.make_apg_networks(
        obs_size,
        action_size,
        preprocess_observations_fn=preprocess_observations_fn,
        hidden_layer_sizes=tuple(cfg.apg.policy_hidden),
    )


def policy_updates(cfg: RunConfig) -> int:
    """Number of APG updates for ``cfg.num_timesteps`` env steps (at least one per evaluation interval)."""
    a = cfg.apg
    return max(int(round(cfg.num_timesteps / (a.num_envs * a.horizon_length))), max(a.num_evals - 1, 1))


def _scalar(x):
    x = np.asarray(x)
    return float(x) if x.size == 1 else x.tolist()


def train(cfg: RunConfig, run_dir, show_progress: bool = True) -> dict:
    """Train and save; returns the summary (also written to ``run_dir/summary.json``)."""
    if cfg.algo != "apg":
        raise ValueError(f"brax_apg.train needs algo='apg', got {cfg.algo!r}")
    run_dir = start_run(cfg, run_dir)
    env = env_from_config(cfg)
    counts = tally.Tally()
    a = cfg.apg
    updates = policy_updates(cfg)
    rows = []
    t0 = time.perf_counter()

    with (run_dir / "metrics.jsonl").open("w") as log:

        def progress(it, metrics):
            row = {
                "step": int(it) * (updates // max(a.num_evals - 1, 1)) * a.num_envs * a.horizon_length,
                "wall_s": round(time.perf_counter() - t0, 2),
            }
            row.update({k: _scalar(v) for k, v in metrics.items() if k.startswith(("eval/", "training/"))})
            row.update({f"train/{k}": v for k, v in counts.as_dict().items()})
            rows.append(row)
            log.write(json.dumps(row) + "\n")
            log.flush()
            if show_progress:
                viol = row["train/violations/position"] + row["train/violations/velocity"]
                print(
                    f"[apg {cfg.shield:>9}] eval {it}/{a.num_evals - 1} {row['wall_s']:7.1f} s | "
                    f"eval reward {row.get('eval/episode_reward', float('nan')):8.2f} | "
                    f"training pos+vel violations {viol}",
                    file=sys.stderr,
                    flush=True,
                )

        with brax_compat("optax.global_norm is deprecated"):
            _, params, _ = _train_apg(env, cfg, counts, updates, progress)
    return finish_run(cfg, run_dir, params, counts, time.perf_counter() - t0, rows)


def _train_apg(env, cfg: RunConfig, counts, updates: int, progress):
    a = cfg.apg
    return brax_apg_train.train(
        environment=env,
        episode_length=cfg.episode_length,
        policy_updates=updates,
        wrap_env_fn=tally.wrap_for_training(counts),
        horizon_length=a.horizon_length,
        num_envs=a.num_envs,
        num_evals=a.num_evals,
        action_repeat=a.action_repeat,
        num_eval_envs=a.num_eval_envs,
        learning_rate=a.learning_rate,
        schedule_decay=a.schedule_decay,
        max_gradient_norm=a.max_gradient_norm,
        normalize_observations=a.normalize_observations,
        deterministic_eval=True,
        seed=cfg.seed,
        network_factory=functools.partial(_networks, cfg),
        progress_fn=progress,
    )


def load_policy(run_dir):
    """``(cfg, policy, params)`` from an APG run folder; ``policy(params, obs, key, t) -> action``."""
    run_dir = Path(run_dir)
    cfg = from_dict(checkpoint.read_meta(run_dir / "params.msgpack"))
    env = env_from_config(cfg)
    nets = _networks(cfg, env.observation_size, env.action_size)
    obs_spec = acme.specs.Array((env.observation_size,), jnp.dtype("float32"))
    template = (running_statistics.init_state(obs_spec), nets.policy_network.init(jax.random.PRNGKey(0)))
    params = checkpoint.load(run_dir / "params.msgpack", template)
    return cfg, deterministic_policy(apg_networks.make_inference_fn(nets)), params
