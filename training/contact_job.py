"""The contact job: train PPO on the planar wall strike with and without the impact-aware speed cap.

``run(out, cfg)`` trains one run per variant (``viability+impact``: the joint-limit shield with the
impact cap of Wang & Kheddar; ``viability``: the same shield without the cap) from the same config
and seed, evaluates each trained policy with its own shield over ``cfg.eval_episodes`` parallel
episodes, and writes ``runs/<variant>/``, ``results.json``, ``results.md`` and
``training_curves.png`` to ``out``. Every strike of training and evaluation is measured
(``WallStrike``: its contact impulse's joint torque over the impulsive-torque bound) and counted
like a limit violation (``training/tally.py``). ``make demo`` runs it as the main job's second task.
"""

from __future__ import annotations

import time
from pathlib import Path

from jaxlimits.training import experiment
from jaxlimits.training.config import CONTACT_ENVS, RunConfig

VARIANTS = {"viability+impact": True, "viability": False}


def run_folders(out, variants=tuple(VARIANTS)) -> dict:
    """Variant name -> its run folder under ``out``."""
    return {name: Path(out) / "runs" / name for name in variants}


def run(out, cfg: RunConfig, show_progress: bool = True, variants=tuple(VARIANTS), quiet: bool = False) -> dict:
    """Train, evaluate and compare ``variants`` (names of ``VARIANTS``); returns the results dict.

    ``quiet``: write the files but do not print the table (the main job prints one table of all tasks).
    """
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown or not variants:
        raise ValueError(f"variants must be names of {tuple(VARIANTS)}, got {variants!r}")
    if cfg.env not in CONTACT_ENVS:
        raise ValueError(f"the contact job needs an env with contacts {CONTACT_ENVS}, got env {cfg.env!r}")
    t0 = time.perf_counter()
    results = {"config": cfg.to_dict(), "variants": {}}
    runs = run_folders(out, variants)
    for name, run_dir in runs.items():
        results["variants"][name] = experiment.train_and_evaluate(
            cfg.override(impact=VARIANTS[name]), run_dir, show_progress
        )
    results["wall_s"] = time.perf_counter() - t0
    table = experiment.format_table({"contact": {"runs": results["variants"]}})
    experiment.write_results(out, results, table, {"training_curves.png": ("contact", runs)}, show=not quiet)
    return results
