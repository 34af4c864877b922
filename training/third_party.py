"""The joint-limit shield under third-party trainers on third-party envs, shielded vs unshielded.

* ``sb3_reacher``: Stable-Baselines3 PPO (``MlpPolicy``, SB3's default hyper-parameters, 4 envs in a
  ``DummyVecEnv``) on Gymnasium's ``Reacher-v5`` (C MuJoCo) inside ``JointLimitShieldWrapper``.
* ``brax_reacher``: Brax PPO (``brax.training.agents.ppo.train``) on Brax's ``reacher`` (MJX backend)
  inside ``JointLimitShield``, with Brax's reacher hyper-parameters scaled down for a CPU.

``shield`` is ``"viability"`` (the shield) or ``"none"`` (the same code path, the command as asked: the
baseline whose violations the shield prevents); ``v_max = 4`` rad/s on both reachers' joints (their
MJCFs give none). Violations are counted at every env step: a step counts for ``position``,
``velocity`` or ``torque`` when its largest excess over the substeps is positive (``info["violation"]``
/ ``state.info["violation"]``); the returns are the envs' own rewards.

    python -m jaxlimits.training.third_party --algo sb3 --timesteps 100000
    python -m jaxlimits.training.third_party --algo brax --timesteps 300000

prints a table for both shields and one JSON line (returns, their ratio shielded/unshielded, violations).
"""

from __future__ import annotations

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402

V_MAX = 4.0  # rad/s, both reachers' joints (as in tests/test_gym_shield.py and tests/test_brax_shield.py)
SHIELDS = ("viability", "none")
KINDS = ("position", "velocity", "torque")
ALGOS = ("sb3", "brax")

# Brax's reacher defaults (brax/training/learner.py, the Brax training notebook) scaled to a CPU: 2048 envs,
# batch 256 x 32 minibatches, unroll 50, episode 1000 with action_repeat 4 there. action_repeat is 1 here
# so that Brax's episode metrics (summed once per policy step) see every env step's violation.
BRAX_PPO = dict(
    num_envs=128,
    batch_size=128,
    num_minibatches=8,
    unroll_length=10,
    num_updates_per_batch=8,
    episode_length=200,
    action_repeat=1,
    discounting=0.95,
    learning_rate=3e-4,
    entropy_cost=1e-3,
    reward_scaling=5.0,
    normalize_observations=True,
    num_evals=6,
    num_eval_envs=128,
)


def _check_shield(shield: str) -> None:
    if shield not in SHIELDS:
        raise ValueError(f"shield must be one of {SHIELDS}, got {shield!r}")


def _sum_tallies(tallies) -> dict:
    """The shields' own running counts (``JointLimitShieldWrapper.tally``) summed over envs: env-steps and
    violating env-steps per kind, and the largest excess of each kind."""
    out = {"steps": sum(t["steps"] for t in tallies)}
    for k in KINDS:
        out[k] = int(sum(t[f"{k}_violations"] for t in tallies))
    for k in KINDS:
        out[f"max_{k}_excess"] = float(max(t[f"max_{k}_excess"] for t in tallies))
    return out


# ---------------------------------------------------------------------------------------------- SB3
def sb3_reacher(shield: str, timesteps: int, seed: int = 0, *, n_envs: int = 4, eval_episodes: int = 100) -> dict:
    """SB3 PPO on shielded ``Reacher-v5`` for ``timesteps`` env-steps, then ``eval_episodes`` deterministic
    episodes on a fresh shielded env.

    Returns ``{"return_mean", "return_std"`` (evaluation, per episode), ``"train_violations"``,
    ``"eval_violations"`` (``{"steps", "position", "velocity", "torque"}`` counts of violating env-steps,
    and ``max_*_excess``), ``"wall_s"`` (training), ``"eval_wall_s"``, ``"env_steps_per_s"`` (training)}.
    SB3 trains whole rollouts (``n_steps = 2048`` per env), so ``train_violations["steps"]`` is
    ``timesteps`` rounded up to a multiple of ``2048 n_envs``.
    """
    import gymnasium
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.evaluation import evaluate_policy

    from jaxlimits.training.sb3 import silent_logger

    from jaxlimits.envs.gym import JointLimitShieldWrapper

    _check_shield(shield)
    torch.set_num_threads(1)

    def vec_env(n, env_seed):
        shields = []

        def make():
            env = JointLimitShieldWrapper(gymnasium.make("Reacher-v5"), v_max=V_MAX, method=shield)
            shields.append(env)
            return env

        return make_vec_env(make, n_envs=n, seed=env_seed), shields

    train_env, train_shields = vec_env(n_envs, seed)
    model = PPO("MlpPolicy", train_env, seed=seed, device="cpu", verbose=0)
    model.set_logger(silent_logger())
    t0 = time.perf_counter()
    model.learn(total_timesteps=timesteps)
    wall = time.perf_counter() - t0
    train = _sum_tallies([s.tally for s in train_shields])
    train_env.close()

    eval_env, eval_shields = vec_env(1, seed + 10_000)
    t0 = time.perf_counter()
    mean, std = evaluate_policy(model, eval_env, n_eval_episodes=eval_episodes, deterministic=True)
    eval_wall = time.perf_counter() - t0
    ev = _sum_tallies([s.tally for s in eval_shields])
    eval_env.close()
    return {
        "algo": "sb3",
        "shield": shield,
        "return_mean": float(mean),
        "return_std": float(std),
        "train_violations": train,
        "eval_violations": ev,
        "eval_episodes": eval_episodes,
        "wall_s": wall,
        "eval_wall_s": eval_wall,
        "env_steps_per_s": train["steps"] / wall,
    }


# --------------------------------------------------------------------------------------------- Brax
def _brax_env(shield: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Brax's "not actively maintained" notice, mjx deprecations
        import brax.envs

        from jaxlimits.envs import JointLimitShield
        from jaxlimits.envs.violation_metrics import ViolationMetrics

        env = JointLimitShield(brax.envs.get_environment("reacher", backend="mjx"), v_max=V_MAX, method=shield)
    return ViolationMetrics(env)


def brax_reacher(shield: str, timesteps: int, seed: int = 0, **ppo) -> dict:
    """Brax PPO on shielded Brax ``reacher`` (MJX) for ``timesteps`` env-steps; ``ppo`` overrides ``BRAX_PPO``.

    Violations during training are counted at every env step (``tally.StepTally`` below Brax's training
    wrappers, reported per batched step to a host ``tally.Tally``); the evaluation ones come from the
    last evaluation's ``progress_fn`` metrics: Brax's evaluator runs ``num_eval_envs`` deterministic
    episodes and reports the mean over them of each metric summed over the episode
    (``eval/episode_count/position`` etc.), so the counts are that mean times ``num_eval_envs`` and
    ``sum_<kind>_excess`` is the excess summed over every evaluation step.

    Returns ``{"return_mean", "return_std"`` (the last evaluation's episode reward), ``"train_violations"``,
    ``"eval_violations"``, ``"wall_s"`` (all of ``ppo.train``: compilation, training and its evaluations),
    ``"env_steps_per_s"`` (training env-steps / ``wall_s``), ``"progress"`` (step, wall time, reward and
    position/velocity violations of every evaluation)}.
    """
    import jax

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        from brax.envs.wrappers import training as brax_training
        from brax.training.agents.ppo import train as ppo_train

    from jaxlimits.training import tally

    _check_shield(shield)
    cfg = dict(BRAX_PPO, **ppo)
    env, eval_env = _brax_env(shield), _brax_env(shield)
    counts = tally.Tally()
    train_wrap = tally.wrap_for_training(counts)

    def wrap_env_fn(e, **kw):
        # the evaluation env is wrapped as Brax would; its violations come from the evaluator's metrics
        return brax_training.wrap(e, **kw) if e is eval_env else train_wrap(e, **kw)

    progress = []
    t0 = time.perf_counter()

    def progress_fn(step, metrics):
        m = {k: float(np.asarray(v)) for k, v in metrics.items() if k.startswith("eval/")}
        progress.append({"step": int(step), "wall_s": time.perf_counter() - t0, **m})

    # brax 0.14.2's PPO calls jax.device_put_replicated (deprecated in the pinned jax) and its observation
    # normaliser relies on rank promotion (the tests make each an error), as in brax_apg.py
    with warnings.catch_warnings(), jax.numpy_rank_promotion("allow"):
        warnings.filterwarnings("ignore", "jax.device_put_replicated is deprecated", DeprecationWarning)
        ppo_train.train(
            environment=env,
            eval_env=eval_env,
            num_timesteps=timesteps,
            seed=seed,
            deterministic_eval=True,
            wrap_env_fn=wrap_env_fn,
            progress_fn=progress_fn,
            **cfg,
        )
    jax.effects_barrier()  # the last host callbacks of the tally
    wall = time.perf_counter() - t0
    last = progress[-1]
    n_eval = cfg["num_eval_envs"]
    ev = {"steps": int(round(last["eval/avg_episode_length"] * n_eval))}
    for k in KINDS:
        ev[k] = int(round(last[f"eval/episode_count/{k}"] * n_eval))
    for k in KINDS:
        ev[f"sum_{k}_excess"] = last[f"eval/episode_shield/{k}"] * n_eval
    tr = counts.as_dict()
    train = {"steps": tr["env_steps"]}
    train.update({k: tr[f"violations/{k}"] for k in KINDS})
    train.update({f"max_{k}_excess": tr[f"max_violation/{k}"] for k in KINDS})
    return {
        "algo": "brax",
        "shield": shield,
        "return_mean": last["eval/episode_reward"],
        "return_std": last["eval/episode_reward_std"],
        "train_violations": train,
        "eval_violations": ev,
        "eval_episodes": n_eval,
        "wall_s": wall,
        "env_steps_per_s": train["steps"] / wall,
        "ppo": cfg,
        "progress": [
            {
                "step": p["step"],
                "wall_s": round(p["wall_s"], 1),
                "return": p["eval/episode_reward"],
                **{k: p[f"eval/episode_count/{k}"] * n_eval for k in ("position", "velocity")},
            }
            for p in progress
        ],
    }


# --------------------------------------------------------------------------------------------- main
def compare(algo: str, timesteps: int, seed: int = 0) -> dict:
    """Both shields with ``algo``; ``{"viability": result, "none": result}``."""
    fn = {"sb3": sb3_reacher, "brax": brax_reacher}[algo]
    return {shield: fn(shield, timesteps, seed) for shield in SHIELDS}


def _table(results: dict) -> str:
    head = (
        f"{'shield':>9} | {'return':>17} | {'train steps':>11} {'pos':>6} {'vel':>6} {'torque':>6} | "
        f"{'eval steps':>10} {'pos':>5} {'vel':>5} {'torque':>6} | {'wall s':>7} {'steps/s':>8}"
    )
    lines = [head, "-" * len(head)]
    for shield, r in results.items():
        t, e = r["train_violations"], r["eval_violations"]
        lines.append(
            f"{shield:>9} | {r['return_mean']:8.3f} +- {r['return_std']:6.3f} | {t['steps']:>11,d} "
            f"{t['position']:>6d} {t['velocity']:>6d} {t['torque']:>6d} | {e['steps']:>10,d} "
            f"{e['position']:>5d} {e['velocity']:>5d} {e['torque']:>6d} | {r['wall_s']:7.1f} {r['env_steps_per_s']:8.0f}"
        )
    return "\n".join(lines)


def summary_line(algo: str, timesteps: int, results: dict) -> dict:
    """The JSON summary: returns, their ratio shielded/unshielded and relative difference, violations, walls."""
    s, u = results["viability"], results["none"]
    return {
        "algo": algo,
        "timesteps": timesteps,
        "return_viability": s["return_mean"],
        "return_none": u["return_mean"],
        "return_ratio_viability_over_none": s["return_mean"] / u["return_mean"],
        "return_rel_diff": (s["return_mean"] - u["return_mean"]) / abs(u["return_mean"]),
        **{
            f"{phase}_violations_{shield}": {k: r[f"{phase}_violations"][k] for k in ("steps",) + KINDS}
            for shield, r in results.items()
            for phase in ("train", "eval")
        },
        **{f"wall_s_{shield}": round(r["wall_s"], 1) for shield, r in results.items()},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=ALGOS, required=True)
    parser.add_argument("--timesteps", type=int, required=True, help="training env-steps per shield")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    results = compare(args.algo, args.timesteps, args.seed)
    print(_table(results))
    for shield, r in results.items():  # Brax: every evaluation during training
        for p in r.get("progress", []):
            print(
                f"{shield:>9} eval at {p['step']:>9,d} steps ({p['wall_s']:6.1f} s): return {p['return']:8.3f}, "
                f"violating steps: position {p['position']:.0f}, velocity {p['velocity']:.0f}"
            )
    print(json.dumps(summary_line(args.algo, args.timesteps, results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
