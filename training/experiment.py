"""What the main job and the contact job share: train one run and evaluate it, one results table, the files.

``train_and_evaluate(cfg, run_dir)`` trains a run and evaluates its deterministic policy with its own
shield over ``cfg.eval_episodes`` episodes (``evaluate_run``: the reload and evaluation alone). ``format_table(sections)`` is the one comparison table of
every job: one row per trained run of every task (``reach``: one per shield, and the scripted IK
reference; ``contact``: one per impact-cap variant), with the training tally over every env-step and
the evaluation row side by side; a task's column that does not apply is ``–`` (the reach has no
strikes). ``write_results`` prints it and writes ``results.json``, ``results.md`` and one PNG of
training curves per task, atomically (``checkpoint.atomic_write_text``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

from jaxlimits.training import algos, brax_ppo, checkpoint, evaluate, plots

# the PNG's panels per task: the contact task's training violations are the strikes over the bound
PANELS = {
    "reach": plots.PANELS,
    "contact": (
        ("eval/return_mean", "evaluation return (mean per episode)"),
        ("eval/success_rate", "evaluation success rate (the wall was struck)"),
        ("train/violations/impact", "strikes over the impulsive-torque bound during training (cumulative)"),
        ("train/violations/velocity", "velocity violations during training (cumulative env-steps)"),
    ),
}


class EvaluatedRun(NamedTuple):
    """A trained run reloaded from its folder and evaluated: its config, env (``env_from_config``),
    deterministic policy, parameters, ``evaluate.evaluate`` row and the evaluation's seed."""

    cfg: object
    env: object
    policy: object
    params: object
    row: dict
    seed: int


def evaluate_run(run_dir, episodes: int | None = None) -> EvaluatedRun:
    """Reload ``run_dir``'s checkpoint and evaluate the deterministic policy with its own shield over
    ``episodes`` episodes (default: its config's ``eval_episodes``), seed ``cfg.seed + 1``."""
    cfg, policy, params = algos.load_policy(run_dir)
    env = brax_ppo.env_from_config(cfg)
    seed = cfg.seed + 1
    episodes = cfg.eval_episodes if episodes is None else episodes
    row = evaluate.evaluate(
        env,
        policy,
        params,
        episodes=episodes,
        episode_length=cfg.episode_length,
        action_repeat=cfg.action_repeat,
        seed=seed,
        # the run's in-training evaluator when this process trained it (PPO) with as many episodes (the same env
        # and policy, built from the same config): the reloaded parameters without a second trace
        evaluator=brax_ppo.training_evaluator(cfg, episodes),
    )
    return EvaluatedRun(cfg, env, policy, params, row, seed)


def train_and_evaluate(cfg, run_dir, show_progress: bool = True) -> dict:
    """Train one run from ``cfg`` into ``run_dir``, then ``evaluate_run`` it over ``cfg.eval_episodes``
    episodes. Returns the training totals, the training wall time and env-steps/s, and the evaluation row."""
    summary = algos.train(cfg, run_dir, show_progress=show_progress)
    return {
        "training": summary["training"],
        "training_wall_s": summary["wall_s"],
        "training_env_steps_per_s": summary["env_steps_per_s"],
        "evaluation": evaluate_run(run_dir, cfg.eval_episodes).row,
    }


HEAD = (
    "| task | shield | training env-steps | training pos / vel violations (max rad, rad/s) | training strikes: "
    "over the bound (max excess) | train wall s (env-steps/s) | eval episodes | eval success | eval return | eval "
    "pos / vel violations (max) | eval strikes: over the bound, worst ratio | eval intervention rad/s² |"
)


def format_table(sections: dict) -> str:
    """Markdown table of ``sections``: task name -> ``{"runs": {shield: train_and_evaluate row}, "reference":
    an optional evaluation row of a scripted policy}``, in order."""
    lines = [HEAD, "|---" * 12 + "|"]
    for task, section in sections.items():
        for name, r in section["runs"].items():
            t = r["training"]
            strikes = (
                f"{t['strikes']:,}: {t['violations/impact']:,} ({t['max_violation/impact']:.3g})"
                if t.get("strikes")
                else "–"
            )
            lines.append(
                f"| {task} | {name} | {t['env_steps']:,} | {t['violations/position']:,} / "
                f"{t['violations/velocity']:,} ({t['max_violation/position']:.3g}, {t['max_violation/velocity']:.3g}) "
                f"| {strikes} | {r['training_wall_s']:.0f} ({r['training_env_steps_per_s']:,.0f}) | "
                f"{_evaluation_cells(r['evaluation'])}"
            )
        if section.get("reference") is not None:
            lines.append(
                f"| {task} | reference: scripted IK, viability | – | – | – | – | {_evaluation_cells(section['reference'])}"
            )
    return "\n".join(lines)


def _evaluation_cells(e: dict) -> str:
    """The table's evaluation columns (and the row's closing bar) of one ``evaluate.evaluate`` row."""
    strikes = f"{e['strikes']:,}: {e['violations/impact']:,}, {e['max_strike_ratio']:.3g}" if e.get("strikes") else "–"
    return (
        f"{e['episodes']:,} | {e['success_rate']:.3f} | {e['return_mean']:.2f} "
        f"| {e['violations/position']:,} / {e['violations/velocity']:,} "
        f"({e['max_violation/position']:.3g}, {e['max_violation/velocity']:.3g}) | {strikes} | "
        f"{e['intervention_mean']:.3g} |"
    )


def write_results(out, results: dict, table: str, curves: dict, show: bool = True) -> None:
    """Print ``table`` (if ``show``); write ``results.json``, ``results.md`` and, per entry of ``curves`` (PNG name ->
    ``(task, {label: run folder})``), the training curves (``plots.plot_runs`` with the task's panels)."""
    out = Path(out)
    if show:
        print(table)
    for png, (task, runs) in curves.items():
        plots.plot_runs(runs, out / png, panels=PANELS[task])
    checkpoint.atomic_write_text(out / "results.json", json.dumps(results, indent=2))
    checkpoint.atomic_write_text(out / "results.md", table + "\n")
