"""Smooth motion: a reach trained under the jerk shield against the viability-only policy.

    taskset -c 0 nice -n 5 .venv/bin/python benchmarks/jerk_training.py [--out results/jerk_training]
    taskset -c 0 nice -n 5 .venv/bin/python benchmarks/jerk_training.py --quick   # tiny smoke run
    .venv/bin/python benchmarks/jerk_training.py --config panda_front_reach_ppo --out results/jerk_panda

Issue 15, item 3. Default: the planar 3-link reach (``envs/assets/planar3.xml``: ``jaxlimits_j_max`` =
500 / 600 / 750 rad/s^3, control period dt = 10 ms); ``--config panda_front_reach_ppo``: the Panda reach
(the datasheet's j_max 3750-10000 rad/s^3, which at dt = 10 ms and the torque-derived a_max cannot bind:
2 a_max / dt <= 820 rad/s^3). Two Brax PPO runs of the same config (default ``planar_reach_ppo``: velocity
actions, IK observation, 400-step episodes) that differ only in the shield: ``viability`` (position, velocity,
acceleration limits) and ``jerk`` (the same plus ``|a_k - a_{k-1}| <= j_max dt``). ``--viability-run DIR``
/ ``--jerk-run DIR`` reuse finished run folders (``jaxlimits train ... --out DIR``) instead of training.

Each policy (deterministic) is evaluated in its own shielded env with the project's evaluator
(``evaluate.evaluate``, ``--episodes`` = 10^4 by default, seed ``cfg.seed + 1`` as ``experiment``): success,
return, position / velocity / jerk violations; the training tally (every env-step of training) is read
from the run's summary. The evaluator returns per-episode summaries only, so the motion statistics come
from a second jitted rollout (``evaluate.play_episode``, the evaluator's own rollout) of the first
``--motion-episodes`` of those evaluation episodes (same keys), recording every control step:

* the *realised* joint acceleration ``a_t``: the shield's output that the env applied over step ``t``
  (``info["a_prev"]`` after the step, i.e. ``a_safe``; the inverse-dynamics torques realise it up to the
  recorded ``accel_error``), not the policy's raw command (whose jerk is also reported, in the JSON only);
* the jerk ``(a_t - a_{t-1}) / dt`` with ``a_{-1} = 0`` (the episode starts at rest, as the env's own
  jerk metric counts it).

``motion_stats`` pools ``|a|`` and ``|jerk|`` over every joint and step: mean, 95th / 99th percentile, max,
and the fraction of steps in which some joint's jerk exceeds its ``j_max`` (the env's test, same float32
arithmetic; checked against the env's ``count/jerk`` metric recorded in the same rollout). Both policies
are measured in the same env numbers (the viability policy's jerk against the same ``j_max``).

Writes ``results.json`` and ``results.md`` (the table, also printed) to ``--out``, the run folders under
``--out/runs/`` when it trains; prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()

SHIELDS = ("viability", "jerk")


def motion_stats(acc, dt: float, j_max, a_prev0=None) -> dict:
    """Acceleration and jerk statistics of realised motion (pure NumPy).

    ``acc``: ``(episodes, steps, n)`` joint accelerations, one per control step [rad/s^2]; ``dt``: the
    control period [s]; ``j_max``: ``(n,)`` [rad/s^3]; ``a_prev0``: the acceleration before the first step
    (default 0: a start at rest). The jerk of step ``t`` is ``(a_t - a_{t-1}) / dt``. A step exceeds the
    jerk limit when some joint has ``|a_t - a_{t-1}| - j_max dt > 0`` computed in ``acc``'s dtype (float32:
    the env's own test, ``ArmReach._limit_metrics``). Percentiles pool every joint and step; ``per_joint``
    gives each joint's max |jerk| and its max over ``j_max``.
    """
    acc = np.asarray(acc)
    if acc.ndim != 3:
        raise ValueError(f"acc must be (episodes, steps, n), got shape {acc.shape}")
    n = acc.shape[-1]
    j_max = np.asarray(j_max, acc.dtype).reshape(n)
    prev0 = (
        np.zeros((acc.shape[0], 1, n), acc.dtype) if a_prev0 is None else np.broadcast_to(a_prev0, (acc.shape[0], 1, n))
    )
    prev = np.concatenate([prev0.astype(acc.dtype), acc[:, :-1]], axis=1)
    delta = np.abs(acc - prev)
    over = np.any(delta - j_max * acc.dtype.type(dt) > 0, axis=-1)  # (episodes, steps)
    jerk = delta.astype(np.float64) / dt
    a_abs = np.abs(acc).astype(np.float64)

    def pooled(x):
        p50, p95, p99 = np.percentile(x, [50, 95, 99])
        return {
            "mean": float(np.mean(x)),
            "p50": float(p50),
            "p95": float(p95),
            "p99": float(p99),
            "max": float(np.max(x)),
        }

    ratio = jerk / j_max.astype(np.float64)
    return {
        "steps": int(over.size),
        "acc": pooled(a_abs),
        "jerk": pooled(jerk),
        "jerk_over_j_max": pooled(ratio),
        "jerk_exceed_steps": int(np.sum(over)),
        "jerk_exceed_fraction": float(np.mean(over)),
        # joint-steps with |jerk| within 1 % of j_max or above: how often the jerk is pinned at the bound
        "jerk_at_bound_fraction": float(np.mean(ratio >= 0.99)),
        "per_joint": {
            "acc_max": np.max(a_abs, axis=(0, 1)).tolist(),
            "jerk_max": np.max(jerk, axis=(0, 1)).tolist(),
            "jerk_max_over_j_max": np.max(ratio, axis=(0, 1)).tolist(),
            "jerk_exceed_fraction": np.mean(delta - j_max * acc.dtype.type(dt) > 0, axis=(0, 1)).tolist(),
        },
    }


def motion_rollout(
    env, policy, params, *, episodes: int, keys_total: int, episode_length: int, action_repeat: int, seed: int
):
    """Per-step realised and commanded accelerations of the first ``episodes`` of the evaluator's episodes.

    The keys are the evaluator's (``split(PRNGKey(seed), keys_total)``), so these are the first episodes of
    its evaluation. Returns NumPy arrays ``a_safe``, ``a_des`` ``(episodes, steps, n)``, ``count_jerk``
    ``(episodes, steps)`` (the env's metric) and ``accel_error`` (its max over the rollout).
    """
    import jax

    from jaxlimits.training import evaluate

    keys = jax.random.split(jax.random.PRNGKey(seed), keys_total)[:episodes]

    def observe(carry, state):
        out = {
            "a_safe": state.info["a_prev"],
            "a_des": state.info["a_des"],
            "count_jerk": state.metrics["count/jerk"],
        }
        return jax.numpy.maximum(carry, state.metrics["accel_error"]), out

    def one(key):
        zero = jax.numpy.zeros((), jax.numpy.float32)
        _, _, err, outs = evaluate.play_episode(env, policy, params, key, episode_length, action_repeat, observe, zero)
        return err, outs

    err, outs = jax.jit(jax.vmap(one))(keys)
    out = {k: np.asarray(v) for k, v in outs.items()}
    out["accel_error"] = float(np.max(np.asarray(err)))
    return out


def run_shield(cfg, run_dir, *, reuse: bool, episodes: int, motion_episodes: int, show_progress: bool) -> dict:
    """Train (unless ``reuse``), evaluate over ``episodes`` and measure the motion of one run."""
    from jaxlimits.training import algos, experiment

    run_dir = Path(run_dir)
    t0 = time.perf_counter()
    if reuse:
        summary = json.loads((run_dir / "summary.json").read_text())
    else:
        summary = algos.train(cfg, run_dir, show_progress=show_progress)
    t_train = time.perf_counter() - t0
    run_cfg, env, policy, params, row, seed = experiment.evaluate_run(run_dir, episodes)
    t0 = time.perf_counter()
    m = min(motion_episodes, episodes)
    roll = motion_rollout(
        env,
        policy,
        params,
        episodes=m,
        keys_total=episodes,
        episode_length=run_cfg.episode_length,
        action_repeat=run_cfg.action_repeat,
        seed=seed,
    )
    t_motion = time.perf_counter() - t0
    lim = env.limits
    realised = motion_stats(roll["a_safe"], env.dt, lim.j_max)
    commanded = motion_stats(roll["a_des"], env.dt, lim.j_max)
    tail = run_cfg.episode_length // 4  # the last quarter of every episode (mostly arrived: holding the target)
    settled = motion_stats(roll["a_safe"][:, -tail:], env.dt, lim.j_max, a_prev0=roll["a_safe"][:, -tail - 1 : -tail])
    env_count = int(np.sum(roll["count_jerk"], dtype=np.float64))
    return {
        "run_dir": str(run_dir),
        "reused": reuse,
        "config": run_cfg.to_dict(),
        "training": summary["training"],
        "training_wall_s": summary["wall_s"],
        "training_env_steps_per_s": summary["env_steps_per_s"],
        "script_train_s": t_train,
        "evaluation": row,
        "motion": {
            "episodes": m,
            "seed": seed,
            "dt": env.dt,
            "j_max": np.asarray(lim.j_max).tolist(),
            "a_max": np.asarray(lim.a_max).tolist(),
            "realised": realised,
            "commanded": commanded,
            "settled_steps": tail,
            "settled": settled,
            "env_count_jerk": env_count,
            "env_count_matches": env_count == realised["jerk_exceed_steps"],
            "accel_error_max": roll["accel_error"],
            "wall_s": t_motion,
        },
    }


HEAD = (
    "| shield | train env-steps | train viol pos / vel / jerk | train wall s | eval episodes | success | return | "
    "eval viol pos / vel / jerk | motion episodes | mean / p95 / p99 / max abs(a) rad/s² | "
    "mean / p50 / p95 / p99 / max abs(jerk) rad/s³ | max jerk / j_max | joint-steps at jerk bound | "
    "steps with jerk > j_max | last quarter: mean abs(a) / mean abs(jerk) |"
)


def format_table(rows: dict) -> str:
    """Markdown table, one line per shield (``rows``: shield -> ``run_shield`` result)."""
    lines = [HEAD, "|---" * 15 + "|"]
    for name, r in rows.items():
        t, e, mo = r["training"], r["evaluation"], r["motion"]
        a, j, st = mo["realised"]["acc"], mo["realised"]["jerk"], mo["settled"]
        lines.append(
            f"| {name} | {t['env_steps']:,} | {t['violations/position']:,} / {t['violations/velocity']:,} / "
            f"{t['violations/jerk']:,} | {r['training_wall_s']:.0f} | {e['episodes']:,} | {e['success_rate']:.3f} | "
            f"{e['return_mean']:.1f} | {e['violations/position']:,} / {e['violations/velocity']:,} / "
            f"{e['violations/jerk']:,} | {mo['episodes']:,} | "
            f"{a['mean']:.2f} / {a['p95']:.2f} / {a['p99']:.2f} / {a['max']:.2f} | "
            f"{j['mean']:.0f} / {j['p50']:.0f} / {j['p95']:.0f} / {j['p99']:.0f} / {j['max']:.0f} | "
            f"{mo['realised']['jerk_over_j_max']['max']:.2f} | {mo['realised']['jerk_at_bound_fraction']:.1%} | "
            f"{mo['realised']['jerk_exceed_fraction']:.2%} | {st['acc']['mean']:.2f} / {st['jerk']['mean']:.0f} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="output folder (default results/jerk_training, --quick: results/jerk_training_quick)")
    p.add_argument(
        "--quick", action="store_true", help="tiny smoke run: config tiny (its eval_episodes), 16 motion episodes"
    )
    p.add_argument("--config", help="training config (default planar_reach_ppo; --quick: tiny)")
    p.add_argument("--steps", type=int, help="num_timesteps of both runs (default: the config's)")
    p.add_argument("--episodes", type=int, help="evaluation episodes (default: the config's eval_episodes)")
    p.add_argument("--motion-episodes", type=int, help="episodes of the motion statistics (default 1000; --quick 16)")
    p.add_argument("--viability-run", metavar="DIR", help="reuse this finished viability run folder")
    p.add_argument("--jerk-run", metavar="DIR", help="reuse this finished jerk run folder")
    p.add_argument("--no-progress", action="store_true", help="no training progress lines on stderr")
    args = p.parse_args(argv)

    from jaxlimits.training import checkpoint, config

    out = Path(args.out or ("results/jerk_training_quick" if args.quick else "results/jerk_training"))
    base = config.load(args.config or ("tiny" if args.quick else "planar_reach_ppo"))
    base = base.override(num_timesteps=args.steps)
    episodes = args.episodes or base.eval_episodes
    motion_episodes = args.motion_episodes or (16 if args.quick else 1000)
    reuse = {"viability": args.viability_run, "jerk": args.jerk_run}
    t0 = time.perf_counter()
    rows = {}
    for shield in SHIELDS:
        run_dir = reuse[shield] or out / "runs" / shield
        if reuse[shield]:
            stored = config.from_dict(json.loads((Path(run_dir) / "config.json").read_text()))
            if stored.shield != shield:
                p.error(f"--{shield}-run {run_dir} was trained with shield {stored.shield!r}")
        rows[shield] = run_shield(
            base.override(shield=shield),
            run_dir,
            reuse=bool(reuse[shield]),
            episodes=episodes,
            motion_episodes=motion_episodes,
            show_progress=not args.no_progress,
        )
    cfgs = {s: {k: v for k, v in r["config"].items() if k != "shield"} for s, r in rows.items()}
    same_config = cfgs["viability"] == cfgs["jerk"]
    table = format_table(rows)
    results = {
        "argv": sys.argv[1:] if argv is None else list(argv),
        "same_config_but_shield": same_config,
        "wall_s": time.perf_counter() - t0,
        "runs": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    checkpoint.atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    checkpoint.atomic_write_text(out / "results.md", table + "\n")
    print(table)
    if not same_config:
        print("WARNING: the two runs differ in more than the shield", file=sys.stderr)
    line = {
        s: {
            "success": r["evaluation"]["success_rate"],
            "eval_jerk_violations": r["evaluation"]["violations/jerk"],
            "train_jerk_violations": r["training"]["violations/jerk"],
            "jerk_p99": r["motion"]["realised"]["jerk"]["p99"],
            "jerk_exceed_fraction": r["motion"]["realised"]["jerk_exceed_fraction"],
            "acc_p99": r["motion"]["realised"]["acc"]["p99"],
        }
        for s, r in rows.items()
    }
    print(json.dumps({"jerk_training": line, "same_config_but_shield": same_config, "wall_s": results["wall_s"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
