"""Brax APG through the shield (exact vs straight-through projection gradient) against PPO at equal wall time.

    taskset -c 1 .venv/bin/python benchmarks/apg_vs_ppo.py --budget-s 900 [--out results/apg_vs_ppo]
    taskset -c 1 .venv/bin/python benchmarks/apg_vs_ppo.py --quick --out results/apg_vs_ppo_quick

Three runs on the planar reach, viability shield, each given about ``--budget-s`` seconds of training
wall time, compilation and the in-training evaluations included. Time axis: every ``metrics.jsonl`` row
carries ``wall_s``, written by ``brax_ppo`` / ``brax_apg``'s progress callbacks: ``perf_counter`` seconds
since the start of their ``train`` when the row is written (after that point's evaluation); the run's
training wall time is ``summary.json``'s ``wall_s`` (to the end of ``train``, the last row's plus saving):

- ``ppo``: config ``planar_reach_ppo`` (``--ppo-steps`` caps ``num_timesteps``; by default the full
  config, whose wall time is reported: it may finish before the budget);
- ``apg exact`` and ``apg straight_through``: config ``planar_reach_apg`` with ``apg.shield_gradient``
  set; Brax APG cannot stop on wall time (its progress callback does not see the parameters), so
  ``num_timesteps`` is chosen from a measured throughput (``apg_timesteps_for_budget``): a short
  calibration run of the same config (3 epochs of 2 updates) gives the fixed cost (setup, first
  evaluation, compilations), the time of one in-training evaluation and the steady env-steps/s.
  ``--calibration RUN_DIR`` calibrates on an earlier such run instead (e.g. ``--quick``'s ``runs/apg_exact``).

Each run is then evaluated with ``experiment.train_and_evaluate`` (the project's jitted evaluator,
deterministic policy, ``eval_episodes`` = 10^4 episodes, success = final end-effector distance < 5 cm).
Writes ``results.json``, ``results.md`` (the table, also printed), ``curves.png`` (in-training evaluation
against training wall seconds) and the run folders ``runs/<name>/``; prints one JSON line of figures.

The returns of PPO and APG are not comparable: the two configs differ in reward (PPO: precision reward,
velocity actions, 400-step episodes, action repeat 2; APG: ``-distance``, acceleration actions, 200-step
episodes). The success criterion is the same.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()

from jaxlimits.training import config, plots  # noqa: E402  (pure Python; the JAX side is imported in main)

RUNS = (("ppo", "ppo", None), ("apg_exact", "apg", "exact"), ("apg_straight_through", "apg", "straight_through"))


def apg_learning_steps(cfg) -> int:
    """Env steps APG learns from: Brax runs ``round(updates / epochs)`` updates per epoch of ``num_envs x horizon``."""
    from jaxlimits.training import brax_apg

    a = cfg.apg
    epochs = max(a.num_evals - 1, 1)
    return int(round(brax_apg.policy_updates(cfg) / epochs)) * epochs * a.num_envs * a.horizon_length


def calibration_from_rows(rows: list) -> dict:
    """Timing of an APG run of >= 3 epochs from its ``metrics.jsonl`` rows (``wall_s`` from the start of ``train``).

    The first two epochs compile the update (the second again: Brax's initial training state is
    weak-typed, the first epoch's output is not), and the in-training evaluator compiles at the first
    two evaluations (the same reason); from the third epoch on the intervals between rows are steady:
    one epoch (``training/walltime`` is Brax's cumulative time inside the epochs) plus one evaluation.
    Returns ``fixed_s`` (the wall time to the third row less two steady intervals: setup and every
    compilation), ``eval_s`` (one steady evaluation) and the steady ``env_steps_per_s``.
    """
    if len(rows) < 4:
        raise ValueError(f"calibration needs >= 4 metrics rows (3 epochs), got {len(rows)}")
    n = len(rows) - 3
    interval = (rows[-1]["wall_s"] - rows[2]["wall_s"]) / n
    epoch = (rows[-1]["training/walltime"] - rows[2]["training/walltime"]) / n
    return {
        "fixed_s": rows[2]["wall_s"] - 2 * interval,
        "eval_s": max(interval - epoch, 0.0),
        "env_steps_per_s": (rows[-1]["step"] - rows[2]["step"]) / n / epoch,
    }


def apg_timesteps_for_budget(cal: dict, budget_s: float, cfg) -> int:
    """``num_timesteps`` for an APG run of ``cfg`` to take about ``budget_s`` of wall time (whole updates per
    epoch, at least one): budget minus the fixed cost and ``num_evals - 1`` evaluations, at the steady rate."""
    a = cfg.apg
    epochs = max(a.num_evals - 1, 1)
    per_update = a.num_envs * a.horizon_length
    left = budget_s - cal["fixed_s"] - epochs * cal["eval_s"]
    per_epoch = max(int(math.floor(left * cal["env_steps_per_s"] / per_update / epochs)), 1)
    return per_epoch * epochs * per_update


def curve(rows: list) -> dict:
    """The in-training evaluation of a run against wall seconds: PPO's rows (the project's evaluator) carry
    ``eval/return_mean`` and ``eval/success_rate``; APG's (Brax's evaluator) ``eval/episode_reward`` only."""
    ret = [r.get("eval/return_mean", r.get("eval/episode_reward")) for r in rows]
    return {
        "wall_s": [r["wall_s"] for r in rows],
        "step": [r["step"] for r in rows],
        "return": ret,
        "success": [r.get("eval/success_rate") for r in rows],
    }


HEAD = (
    "| run | gradient | training env-steps | training wall s | env-steps/s | eval success | eval return "
    "| violations pos / vel: training | violations pos / vel: eval |"
)


def format_table(results: dict) -> str:
    lines = [HEAD, "|---" * 9 + "|"]
    for name, r in results["runs"].items():
        t, e = r["training"], r["evaluation"]
        lines.append(
            f"| {name} | {r['gradient']} | {r['learning_env_steps']:,} | {r['training_wall_s']:.0f} | "
            f"{r['learning_env_steps'] / r['training_wall_s']:,.0f} | {e['success_rate']:.3f} | {e['return_mean']:.2f} "
            f"| {t['violations/position']} / {t['violations/velocity']} "
            f"| {e['violations/position']} / {e['violations/velocity']} |"
        )
    return "\n".join(lines)


def plot_curves(results: dict, out_png) -> Path:
    """Eval return (PPO and APG on their own axes: different rewards) and success against training wall s;
    the success markers are the final evaluations (``eval_episodes`` each), the dotted line the budget."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), sharex=True)
    episodes = max(r["evaluation"]["episodes"] for r in results["runs"].values())
    titles = (
        "APG: in-training eval return\n(Brax evaluator, 256 episodes: -distance, 200 steps)",
        "PPO: in-training eval return\n(128 episodes: precision reward, 400 steps)",
        f"success rate (final distance < 5 cm)\nline: in-training eval; star: {episodes:,} episodes after training",
    )
    for i, (name, r) in enumerate(results["runs"].items()):
        c, color = r["curve"], f"C{i}"
        ax = axes[0] if r["algo"] == "apg" else axes[1]
        ax.plot(c["wall_s"], c["return"], marker="o", ms=3, color=color, label=name)
        if any(s is not None for s in c["success"]):
            axes[2].plot(c["wall_s"], c["success"], marker="o", ms=3, color=color)
        axes[2].plot(
            [r["training_wall_s"]], [r["evaluation"]["success_rate"]], marker="*", ms=12, color=color, label=name
        )
    for ax, title in zip(axes, titles):
        ax.axvline(results["budget_s"], color="0.6", ls=":", lw=1)
        ax.set_xlim(0, 1.05 * max(results["budget_s"], *(r["training_wall_s"] for r in results["runs"].values())))
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("training wall s (one core)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    out_png = Path(out_png)
    fig.savefig(out_png, dpi=80)
    plt.close(fig)
    return out_png


def run_configs(args) -> dict:
    """name -> config of the three runs (``--quick``: tiny budgets)."""
    ppo = config.load("planar_reach_ppo")
    apg = config.load("planar_reach_apg")
    if args.quick:
        ppo = ppo.override(num_timesteps=1, eval_episodes=256, ppo={"num_evals": 2})
        apg = apg.override(eval_episodes=256, apg={"num_evals": 4})
    if args.ppo_steps:
        ppo = ppo.override(num_timesteps=args.ppo_steps)
    return {"ppo": ppo, "apg": apg}


def calibrate(apg_cfg, out: Path, show: bool) -> dict:
    """A short APG run of ``apg_cfg`` (3 epochs of 2 updates) and its timing (``calibration_from_rows``)."""
    from jaxlimits.training import algos

    a = apg_cfg.apg
    cfg = apg_cfg.override(num_timesteps=6 * a.num_envs * a.horizon_length, apg={"num_evals": 4})
    algos.train(cfg, out, show_progress=show)
    return calibration_from_rows(plots.read_rows(out))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--budget-s", type=float, default=900.0, help="training wall seconds per run")
    p.add_argument("--out", default="results/apg_vs_ppo")
    p.add_argument("--quick", action="store_true", help="smoke run: tiny budgets, 256 evaluation episodes")
    p.add_argument("--ppo-steps", type=int, help="cap PPO's num_timesteps (default: the full config)")
    p.add_argument(
        "--calibration", metavar="RUN_DIR", help="an APG run folder of >= 3 epochs of the same config to calibrate on"
    )
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--replot", action="store_true", help="only redraw OUT/curves.png from OUT/results.json")
    args = p.parse_args(argv)
    if args.replot:
        plot_curves(json.loads((Path(args.out) / "results.json").read_text()), Path(args.out) / "curves.png")
        return 0
    from jaxlimits.training import brax_ppo, checkpoint, experiment

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    show = not args.no_progress
    t0 = time.perf_counter()
    cfgs = run_configs(args)

    if args.quick:  # the quick run's exact APG run (3 epochs of 2 updates) is itself the calibration run
        cal = None
        apg_steps = 6 * cfgs["apg"].apg.num_envs * cfgs["apg"].apg.horizon_length
    else:
        if args.calibration:
            cal = calibration_from_rows(plots.read_rows(args.calibration))
        else:
            cal = calibrate(cfgs["apg"], out / "calibration", show)
        apg_steps = apg_timesteps_for_budget(cal, args.budget_s, cfgs["apg"])

    results = {"budget_s": args.budget_s, "quick": args.quick, "runs": {}}
    for name, algo, gradient in RUNS:
        if algo == "ppo":
            cfg = cfgs["ppo"]
        else:
            cfg = cfgs["apg"].override(num_timesteps=apg_steps, apg={"shield_gradient": gradient})
        print(f"== {name}: {cfg.num_timesteps:,} num_timesteps", file=sys.stderr, flush=True)
        r = experiment.train_and_evaluate(cfg, out / "runs" / name, show_progress=show)
        rows = plots.read_rows(out / "runs" / name)
        if algo == "ppo":
            learning = brax_ppo.total_env_steps(cfg)
        else:
            learning = apg_learning_steps(cfg)
        results["runs"][name] = {
            "algo": algo,
            "gradient": gradient or "– (no gradient through the env)",
            "num_timesteps": cfg.num_timesteps,
            "learning_env_steps": learning,
            **r,
            "curve": curve(rows),
        }
        if args.quick and name == "apg_exact":
            cal = calibration_from_rows(rows)
    results["calibration"] = cal
    results["ppo_full_config"] = not args.ppo_steps
    results["wall_s"] = time.perf_counter() - t0
    table = format_table(results)
    print(table)
    plot_curves(results, out / "curves.png")
    checkpoint.atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    checkpoint.atomic_write_text(out / "results.md", table + "\n")
    figures = {
        name: {
            "env_steps": r["learning_env_steps"],
            "wall_s": round(r["training_wall_s"], 1),
            "success": r["evaluation"]["success_rate"],
            "return": round(r["evaluation"]["return_mean"], 2),
            "violations_train": r["training"]["violations/position"] + r["training"]["violations/velocity"],
            "violations_eval": r["evaluation"]["violations/position"] + r["evaluation"]["violations/velocity"],
        }
        for name, r in results["runs"].items()
    }
    print(json.dumps({"budget_s": args.budget_s, "runs": figures}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
