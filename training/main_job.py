"""The main job: train PPO on planar reach with and without the shield, evaluate both, compare.

``run(out)`` trains one run per shield (default ``viability`` and ``none``) from the same config and
seed, evaluates each trained policy with its own shield over ``cfg.eval_episodes`` parallel episodes
(``evaluate.Evaluator``), and writes to ``out``: ``runs/<shield>/`` (each run's folder),
``results.json`` (training totals and evaluation rows), ``results.md`` (the table) and
``training_curves.png``. It prints the comparison table. With velocity actions and the IK
observation it also evaluates ``evaluate.ik_reference_policy`` (a greedy scripted reach controller,
viability shield, same episodes) as the reference row a learned policy is measured against.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from jaxlimits.training import algos, brax_ppo, evaluate, plots
from jaxlimits.training.config import RunConfig


def run(out, cfg: RunConfig, shields=("viability", "none"), show_progress: bool = True) -> dict:
    out = Path(out)
    t0 = time.perf_counter()
    results = {"config": cfg.to_dict(), "shields": {}}
    runs = {}
    for shield in shields:
        runs[shield] = out / "runs" / shield
        results["shields"][shield] = train_and_evaluate(cfg.override(shield=shield), runs[shield], show_progress)
    if cfg.action_mode == "velocity" and cfg.ik_observation:
        env = brax_ppo.env_from_config(cfg.override(shield="viability"))
        policy = evaluate.ik_reference_policy(env.action_size, env.limits.v_max)
        results["reference"] = evaluate.evaluate(
            env, policy, None, episodes=cfg.eval_episodes, episode_length=cfg.episode_length, seed=cfg.seed + 1
        )
    results["wall_s"] = time.perf_counter() - t0
    write_results(out, results, format_results(results), runs)
    return results


def train_and_evaluate(cfg: RunConfig, run_dir, show_progress: bool = True) -> dict:
    """Train one run from ``cfg`` into ``run_dir``, reload its checkpoint and evaluate the deterministic
    policy with its own shield over ``cfg.eval_episodes`` episodes (seed ``cfg.seed + 1``). Returns the
    training totals, the training wall time and env-steps/s, and the evaluation row."""
    summary = algos.train(cfg, run_dir, show_progress=show_progress)
    run_cfg, policy, params = algos.load_policy(run_dir)
    row = evaluate.evaluate(
        brax_ppo.env_from_config(run_cfg),
        policy,
        params,
        episodes=cfg.eval_episodes,
        episode_length=cfg.episode_length,
        action_repeat=cfg.action_repeat,
        seed=cfg.seed + 1,
    )
    return {
        "training": summary["training"],
        "training_wall_s": summary["wall_s"],
        "training_env_steps_per_s": summary["env_steps_per_s"],
        "evaluation": row,
    }


def write_results(out: Path, results: dict, table: str, runs: dict) -> None:
    """Print ``table``; write ``results.json``, ``results.md`` and ``training_curves.png`` (one curve per run
    folder in ``runs``: name -> folder) to ``out``."""
    print(table)
    plots.plot_runs(runs, out / "training_curves.png")
    (out / "results.json").write_text(json.dumps(results, indent=2))
    (out / "results.md").write_text(table + "\n")


def format_results(results: dict) -> str:
    """Markdown table: per shield, training violations (all env-steps) and evaluation figures."""
    head = (
        "| shield | training env-steps | training pos / vel violations (max rad, rad/s) | train wall s (env-steps/s) "
        "| eval episodes | eval success | eval return | eval pos / vel violations (max) | eval intervention rad/s² |"
    )
    lines = [head, "|---" * 9 + "|"]
    for shield, r in results["shields"].items():
        t = r["training"]
        lines.append(
            f"| {shield} | {t['env_steps']:,} | {t['violations/position']:,} / {t['violations/velocity']:,} "
            f"({t['max_violation/position']:.3g}, {t['max_violation/velocity']:.3g}) "
            f"| {r['training_wall_s']:.0f} ({r['training_env_steps_per_s']:,.0f}) | {_evaluation_cells(r['evaluation'])}"
        )
    if "reference" in results:
        lines.append(f"| reference: scripted IK, viability | – | – | – | {_evaluation_cells(results['reference'])}")
    return "\n".join(lines)


def _evaluation_cells(e: dict) -> str:
    """The table's evaluation columns (and the row's closing bar) of one ``evaluate.evaluate`` row."""
    return (
        f"{e['episodes']:,} | {e['success_rate']:.3f} | {e['return_mean']:.2f} "
        f"| {e['violations/position']:,} / {e['violations/velocity']:,} "
        f"({e['max_violation/position']:.3g}, {e['max_violation/velocity']:.3g}) | {e['intervention_mean']:.3g} |"
    )
