"""Brax PPO with the shield inside the env, every violation counted, msgpack checkpoints.

``train(cfg, run_dir)`` trains ``brax.training.agents.ppo`` on ``make_env(cfg.env, cfg.shield)``
(the ``SafetyWrapper`` sits inside the env, so every physics step of training and of PPO's own
evaluations is shielded), wrapped with ``tally.wrap_for_training`` so that violations are counted
at every env step. It writes to ``run_dir``: ``config.json``, ``metrics.jsonl`` (one line per PPO
evaluation: step, wall time, evaluation return/distance/violations, the running violation totals
of training), ``checkpoint.msgpack`` (rewritten at every evaluation: the training checkpoint
``resume`` continues from), ``params.msgpack`` (``checkpoint.save``) and ``summary.json``; every
file but the appended ``metrics.jsonl`` is written atomically (``checkpoint.atomic_write_*``).

``resume(run_dir)`` continues a run killed at any moment from its last ``checkpoint.msgpack``:
the parameters, the observation normaliser, the env-step count, the violation tallies and the
metrics rows continue exactly; the Adam moments restart from zero, the RNG stream is a new one
(seeded from the seed and the step), and the envs start fresh episodes (Brax's ``restore_params``
restores the networks only). At most one evaluation interval of work is lost.

``load_policy(run_dir)`` rebuilds the networks from the stored config and returns
``(policy, params)`` for ``evaluate.evaluate``.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
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
from jaxlimits.training.config import CONTACT_ENVS, ROBOT_ACTION_MODES, ROBOT_ENVS, RunConfig, from_dict


def make_base_env(name: str, **kwargs):
    """The unshielded env (an ``ArmReach``; ``planar_wall``: a ``WallStrike``) for a config's ``env`` name
    (``kwargs`` go to its constructor)."""
    from jaxlimits.envs import make_panda_front_reach, make_panda_reach, make_planar_reach, make_planar_wall_strike

    makers = {
        "planar_reach": make_planar_reach,
        "panda_reach": make_panda_reach,
        "panda_front_reach": make_panda_front_reach,
        "planar_wall": make_planar_wall_strike,
    }
    return makers[name](**kwargs)


def make_env(
    name: str,
    shield: str,
    action_mode: str | None = None,
    shield_gradient: str = "exact",
    impact: bool = False,
    **kwargs,
):
    """``SafetyWrapper(env(**kwargs), method=shield, gradient=shield_gradient, impact=impact)`` with the
    policy's actions meaning ``action_mode`` (``jaxlimits.envs.actions``): the env every algorithm
    and the evaluator see. ``impact``: the impact-aware speed cap (envs with contacts). A ``ROBOT_ENVS``
    name gets ``_robot_env`` instead (the one shield over ``Reach``; its actions ``config.ROBOT_ACTION_MODES``).
    ``action_mode=None``: ``"acceleration"``, for a ``ROBOT_ENVS`` name the first of its ``ROBOT_ACTION_MODES``."""
    from jaxlimits.envs import SafetyWrapper
    from jaxlimits.envs.actions import with_action_mode

    if name in ROBOT_ENVS:
        return _robot_env(name, shield, action_mode or ROBOT_ACTION_MODES[name][0], impact=impact, **kwargs)
    action_mode = action_mode or "acceleration"
    shielded = SafetyWrapper(
        make_base_env(name, **kwargs), method=shield, gradient=shield_gradient, impact=True if impact else None
    )
    return with_action_mode(shielded, action_mode)


def _robot_env(name: str, shield: str, action_mode: str, impact: bool = False, **kwargs):
    """``ViolationMetrics(JointLimitShield(Reach(action=action_mode, **kwargs), method=shield))`` for a
    ``ROBOT_ENVS`` name: the any-robot shield around the any-robot task (``Reach``; ``planar_robot_wall``: ``Strike``,
    with ``impact`` its impact cap, ``strike_point``, and under ``"none"`` its strikes measured), its record under the metric names the trainers and the
    evaluator read (``jaxlimits.envs.violation_metrics``). ``"velocity"`` (the planar arm): ``VelocityActions`` over
    the shield of the task's ``action="acceleration"``, as over ``SafetyWrapper``."""
    from jaxlimits.envs import JointLimitShield
    from jaxlimits.envs.actions import with_action_mode
    from jaxlimits.envs.reach import make_planar_robot_reach, make_servo_panda_front_reach
    from jaxlimits.envs.strike import make_planar_robot_wall, strike_point
    from jaxlimits.envs.violation_metrics import ViolationMetrics
    from jaxlimits.training.campaign_rows import shield_impact

    makers = {
        "servo_panda_front_reach": make_servo_panda_front_reach,
        "planar_robot_reach": make_planar_robot_reach,
        "planar_robot_wall": make_planar_robot_wall,
    }
    if name in CONTACT_ENVS:
        kwargs.pop("precision_reward", None)  # a reach option (the config refuses it for contact envs)
    reach_action = "acceleration" if action_mode == "velocity" else action_mode
    task = makers[name](action=reach_action, **kwargs)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the torque-derived a_max's quantile notice
        # the cap where the config asks for it; unshielded, a contact task's strikes measured (not capped), as the
        # campaign's none rows: an unshielded run's evaluation counts them too
        point = strike_point(task) if name in CONTACT_ENVS else None
        point = shield_impact(shield + ("+impact" if impact else ""), point)
        shielded = JointLimitShield(task, method=shield, impact=point)
    return ViolationMetrics(with_action_mode(shielded, action_mode) if action_mode == "velocity" else shielded)


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


CHECKPOINT = "checkpoint.msgpack"  # the training checkpoint in a run folder (``resume`` reads it)


# this process's last PPO run's in-training evaluator, ``(key, Evaluator)`` (at most one, so a process that trains
# many runs holds one compiled evaluation): ``training_evaluator``
_LAST_EVALUATOR: list = []


def _evaluator_key(cfg: RunConfig, episodes: int) -> tuple:
    return json.dumps(cfg.to_dict(), sort_keys=True), int(episodes)


def training_evaluator(cfg: RunConfig, episodes: int):
    """The ``evaluate.Evaluator`` this process's last PPO run evaluated with, if it was built for ``cfg`` and
    ``episodes`` (else ``None``): a final evaluation of the same env, policy and episode count reuses it and
    skips tracing the evaluation again (~5 s for the planar arm, ~7 s for the servo Panda; its compilation
    was already a persistent-cache hit)."""
    if _LAST_EVALUATOR and _LAST_EVALUATOR[0][0] == _evaluator_key(cfg, episodes):
        return _LAST_EVALUATOR[0][1]
    return None


class _Progress:
    """Brax PPO's ``policy_params_fn``: evaluate the current policy, log a ``metrics.jsonl`` row, save the
    training checkpoint, draw the bar.

    Called at step 0 and after every training epoch group (``num_evals`` times). The evaluation is
    ``evaluate.Evaluator`` (deterministic policy, ``eval_episodes_during_training`` episodes, the
    same shielded env), compiled once; its violations are counted in the row, apart from training's.
    The row is appended (and flushed) before ``checkpoint.msgpack`` is replaced, so the checkpoint's
    step always has its row; rows past the checkpoint (a kill in between) are dropped on resume.

    ``start``: the meta of the checkpoint a resumed run starts from (``None``: a fresh run); Brax's
    steps then count from it, and its own step-0 call (the checkpoint's step, already logged) is skipped.
    """

    def __init__(self, cfg: RunConfig, run_dir: Path, counts: tally.Tally, env, show: bool, start: dict | None = None):
        self.cfg, self.run_dir, self.counts, self.env, self.show = cfg, run_dir, counts, env, show
        self.step0 = start["step"] if start else 0
        self.wall0 = start["wall_s"] if start else 0.0
        self.resumes = start["resumes"] + 1 if start else 0
        self.seed = resume_seed(cfg.seed, self.step0) if start else cfg.seed
        self.rows = _kept_rows(run_dir / "metrics.jsonl", start) if start else []
        path = run_dir / "metrics.jsonl"
        checkpoint.atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in self.rows))
        self.file = path.open("a")
        self.t0 = time.perf_counter()
        self.evaluator = None
        # the caller's rank-promotion setting: Brax's trainer runs under "allow" (``brax_compat``), and an
        # evaluation traced there would not match the final one's trace context (a second trace and compile)
        self.rank_promotion = jax.config.jax_numpy_rank_promotion

    def wall(self) -> float:
        """Seconds of training so far: the checkpoint's (resumed runs) plus this process's."""
        return self.wall0 + time.perf_counter() - self.t0

    def __call__(self, step, make_policy, params):
        step = self.step0 + int(step)
        if self.rows and step <= self.rows[-1]["step"]:
            return  # a resumed run's first call: the checkpoint's step, logged before the kill
        jax.effects_barrier()  # every host callback of the tally for the steps so far has run
        if self.evaluator is None:
            policy = deterministic_policy(make_policy)
            self.evaluator = evaluate.Evaluator(
                self.env,
                policy,
                episodes=self.cfg.num_eval_envs,
                episode_length=self.cfg.episode_length,
                action_repeat=self.cfg.action_repeat,
            )
            _LAST_EVALUATOR[:] = [(_evaluator_key(self.cfg, self.cfg.num_eval_envs), self.evaluator)]
        # strong types: Brax's step-0 parameters hold weak-typed scalars, later ones do not (one trace, not two)
        params = jax.tree.map(lambda x: jnp.asarray(x).astype(jnp.asarray(x).dtype), params)
        with jax.numpy_rank_promotion(self.rank_promotion):
            per = self.evaluator(params, seed=10_000 + len(self.rows))
        ev = evaluate.summarize(per, self.cfg.episode_length)
        row = {"step": step, "wall_s": round(self.wall(), 2)}
        row.update({f"eval/{k}": v for k, v in ev.items()})
        row.update({f"train/{k}": v for k, v in self.counts.as_dict().items()})
        self.rows.append(row)
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
        meta = {
            "kind": "ppo-training-checkpoint",
            "config": self.cfg.to_dict(),
            "step": step,
            "wall_s": row["wall_s"],
            "tally": self.counts.state(),
            "row": row,
            "seed": self.seed,  # the Brax seed of the process that wrote it
            "resumes": self.resumes,
        }
        checkpoint.save(self.run_dir / CHECKPOINT, params, meta)
        if self.show:
            total = total_env_steps(self.cfg)
            frac = min(step / total, 1.0)
            bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
            viol = row["train/violations/position"] + row["train/violations/velocity"]
            print(
                f"[{self.cfg.shield + ('+impact' if self.cfg.impact else ''):>9}] [{bar}] {step:>10,d}/{total:,d} steps "
                f"{row['wall_s']:7.1f} s | eval return {ev['return_mean']:8.2f} success {ev['success_rate']:.2f} | "
                f"training pos+vel violations {viol}",
                file=sys.stderr,
                flush=True,
            )

    def close(self):
        self.file.close()


def resume_seed(seed: int, step: int) -> int:
    """The Brax seed of a run resumed at ``step``: a fresh, reproducible stream (Brax exposes no RNG state)."""
    digest = hashlib.sha256(f"jaxlimits-resume:{seed}:{step}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def _kept_rows(path: Path, start: dict) -> list:
    """The ``metrics.jsonl`` rows before the checkpoint's step, then the checkpoint's own row.

    A truncated last line (a kill mid-write) is dropped; rows past the checkpoint are dropped (that
    work is redone); a damaged line elsewhere raises ``ValueError`` naming the file.
    """
    lines = path.read_text().splitlines() if path.exists() else []
    rows = []
    for i, line in enumerate(lines):
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            if i == len(lines) - 1:
                break
            raise ValueError(f"{path} line {i + 1} is not JSON: {exc}") from exc
        if row["step"] < start["step"]:
            rows.append(row)
    return rows + [start["row"]]


def start_run(cfg: RunConfig, run_dir) -> Path:
    """Create the run folder and write its ``config.json`` (every algorithm's run folder starts so)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint.atomic_write_text(run_dir / "config.json", json.dumps(cfg.to_dict(), indent=2))
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
    checkpoint.atomic_write_text(run_dir / "summary.json", json.dumps(summary, indent=2))
    return summary


@contextlib.contextmanager
def brax_compat(*deprecated: str):
    """What brax 0.14.2's trainers need under the pinned versions: they call ``jax.device_put_replicated``
    (and APG ``optax.global_norm``: pass it in ``deprecated``), deprecated there (an error where warnings
    are errors, as in the tests), and their observation normaliser relies on rank promotion.

    ``jax.device_put_replicated`` is replaced meanwhile by ``_replicated``, which gives the arrays the
    sharding of Brax's pmapped outputs: with the original's (a mesh axis of its own), the first training
    epoch's inputs differ from every later epoch's and the epoch, the costliest program, compiled twice
    (measured: 8.6 and 8.1 s on the tiny config)."""
    with warnings.catch_warnings(), jax.numpy_rank_promotion("allow"):
        for message in ("jax.device_put_replicated is deprecated", *deprecated):
            warnings.filterwarnings("ignore", message, DeprecationWarning)
        had = "device_put_replicated" in vars(jax)  # else a deprecated name served by jax's module __getattr__
        original = vars(jax).get("device_put_replicated")
        jax.device_put_replicated = _replicated
        try:
            yield
        finally:
            if had:
                jax.device_put_replicated = original
            else:
                del jax.device_put_replicated


def _replicated(tree, devices):
    """``jax.device_put_replicated(tree, devices)`` laid out as a pmap over Brax's axis name lays out its outputs."""
    axis = getattr(brax_ppo_train, "_PMAP_AXIS_NAME", "i")
    stacked = jax.tree.map(lambda x: jnp.stack([jnp.asarray(x)] * len(devices)), tree)
    return jax.pmap(lambda t: t, axis_name=axis, devices=devices)(stacked)


def train(cfg: RunConfig, run_dir, show_progress: bool = True) -> dict:
    """Train and save; returns the summary (also written to ``run_dir/summary.json``)."""
    return _train(cfg, start_run(cfg, run_dir), show_progress)


def resume(run_dir, show_progress: bool = True) -> dict:
    """Continue the run in ``run_dir`` (killed at any moment) from its ``checkpoint.msgpack``; the summary.

    The config is the checkpoint's (the run's own). Continues exactly: the parameters (policy, value),
    the observation normaliser, the env-step count (the total is the configured one), the violation
    tallies and the metrics rows. Does not: the Adam moments and step count (restart at zero), the
    RNG stream (Brax's, re-seeded with ``resume_seed(seed, step)``), the envs' episodes in progress
    (fresh resets). A run killed before its first checkpoint starts again from ``config.json``; a
    finished one is written again from its last checkpoint. A damaged checkpoint raises ``ValueError``.
    """
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT
    if not path.exists():
        if not (run_dir / "config.json").exists():
            raise FileNotFoundError(f"{run_dir} is not a run folder (no {CHECKPOINT}, no config.json)")
        cfg = from_dict(json.loads((run_dir / "config.json").read_text()))
        if cfg.algo != "ppo":
            raise ValueError(f"resume continues PPO runs; {run_dir} is an {cfg.algo!r} run")
        return train(cfg, run_dir, show_progress)
    meta = checkpoint.read_meta(path)
    if meta.get("kind") != "ppo-training-checkpoint":
        raise ValueError(f"{path} is not a PPO training checkpoint")
    cfg = from_dict(meta["config"])
    env = env_from_config(cfg)
    params, meta = checkpoint.load_with_meta(path, _template(cfg, env))
    params = jax.tree.map(jnp.asarray, params)
    return _train(cfg, run_dir, show_progress, start=(params, meta), env=env)


def _train(cfg: RunConfig, run_dir: Path, show_progress: bool, start=None, env=None) -> dict:
    """Brax PPO from step 0 (``start=None``) or from a checkpoint's ``(params, meta)``."""
    env = env if env is not None else env_from_config(cfg)
    params, meta = start if start else (None, None)
    counts = tally.Tally.from_state(meta["tally"]) if meta else tally.Tally()
    p = cfg.ppo
    epochs = max(p.num_evals - 1, 1)
    per_epoch = total_env_steps(cfg) // epochs
    if meta and (meta["step"] % per_epoch or meta["step"] > epochs * per_epoch):
        raise ValueError(
            f"checkpoint step {meta['step']} is not an evaluation point of its config ({per_epoch} steps each)"
        )
    remaining = epochs - (meta["step"] // per_epoch if meta else 0)
    progress = _Progress(cfg, run_dir, counts, env, show_progress, meta)
    try:
        if remaining > 0:
            with brax_compat():
                _, params, _ = brax_ppo_train.train(
                    environment=env,
                    # the remaining epochs, each as long as the configured run's (Brax rounds per epoch)
                    num_timesteps=remaining * per_epoch,
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
                    num_evals=remaining + 1,
                    run_evals=False,
                    seed=progress.seed,
                    restore_params=params,
                    policy_params_fn=progress,
                    wrap_env_fn=tally.wrap_for_training(counts),
                    network_factory=functools.partial(_networks, cfg),
                )
    finally:
        progress.close()
    return finish_run(cfg, run_dir, params, counts, progress.wall(), progress.rows)


def _template(cfg: RunConfig, env):
    """The ``(normalizer, policy, value)`` pytree a checkpoint's arrays are restored into."""
    nets = _networks(cfg, env.observation_size, env.action_size)
    key = jax.random.PRNGKey(0)
    obs_spec = acme.specs.Array((env.observation_size,), jnp.dtype("float32"))
    return (running_statistics.init_state(obs_spec), nets.policy_network.init(key), nets.value_network.init(key))


def load_policy(run_dir):
    """``(cfg, policy, params)`` from a run folder; ``policy(params, obs, key, t) -> action`` (deterministic)."""
    run_dir = Path(run_dir)
    cfg = from_dict(checkpoint.read_meta(run_dir / "params.msgpack"))
    env = env_from_config(cfg)
    nets = _networks(cfg, env.observation_size, env.action_size)
    params = checkpoint.load(run_dir / "params.msgpack", _template(cfg, env))
    return cfg, deterministic_policy(ppo_networks.make_inference_fn(nets)), params


def deterministic_policy(make_policy):
    """The evaluator's ``policy(params, obs, key, t) -> action`` from a Brax ``make_policy``
    (``make_inference_fn(networks)``), deterministic; shared by PPO and APG."""

    def policy(params, obs, key, t):
        del t
        return make_policy(params, deterministic=True)(obs, key[1])[0]

    return policy
