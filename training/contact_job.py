"""The contact job: train PPO on the planar wall strike with and without the impact-aware speed cap.

``run(out, cfg)`` trains one run per variant (``viability+impact``: the joint-limit shield with the
impact cap of Wang & Kheddar; ``viability``: the same shield without the cap) from the same config
and seed, evaluates each trained policy with its own shield over ``cfg.eval_episodes`` parallel
episodes, and writes ``runs/<variant>/``, ``results.json``, ``results.md`` and
``training_curves.png`` to ``out``. Every strike of training and evaluation is measured
(``WallStrike``: its contact impulse's joint torque over the impulsive-torque bound) and counted
like a limit violation (``training/tally.py``).
"""

from __future__ import annotations

import time
from pathlib import Path

from jaxlimits.training import main_job
from jaxlimits.training.config import CONTACT_ENVS, RunConfig

VARIANTS = {"viability+impact": True, "viability": False}


def run(out, cfg: RunConfig, show_progress: bool = True, variants=tuple(VARIANTS)) -> dict:
    """Train, evaluate and compare ``variants`` (names of ``VARIANTS``); returns the results dict."""
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown or not variants:
        raise ValueError(f"variants must be names of {tuple(VARIANTS)}, got {variants!r}")
    if cfg.env not in CONTACT_ENVS:
        raise ValueError(f"the contact job needs an env with contacts {CONTACT_ENVS}, got env {cfg.env!r}")
    out = Path(out)
    t0 = time.perf_counter()
    results = {"config": cfg.to_dict(), "variants": {}}
    runs = {}
    for name in variants:
        runs[name] = out / "runs" / name
        results["variants"][name] = main_job.train_and_evaluate(
            cfg.override(impact=VARIANTS[name]), runs[name], show_progress
        )
    results["wall_s"] = time.perf_counter() - t0
    main_job.write_results(out, results, format_results(results), runs)
    return results


def format_results(results: dict) -> str:
    """Markdown table: per variant, training strikes and violations (all env-steps) and the evaluation."""
    head = (
        "| shield | training env-steps | training strikes: over the bound (max excess) | training pos / vel "
        "violations (max rad, rad/s) | train wall s | eval episodes | eval success | eval return | eval strikes: "
        "over the bound, worst ratio | eval pos / vel violations (max) |"
    )
    lines = [head, "|---" * 10 + "|"]
    for name, r in results["variants"].items():
        t, e = r["training"], r["evaluation"]
        lines.append(
            f"| {name} | {t['env_steps']:,} | {t['strikes']:,}: {t['violations/impact']:,} "
            f"({t['max_violation/impact']:.3g}) | {t['violations/position']:,} / {t['violations/velocity']:,} "
            f"({t['max_violation/position']:.3g}, {t['max_violation/velocity']:.3g}) | {r['training_wall_s']:.0f} "
            f"| {e['episodes']:,} | {e['success_rate']:.3f} | {e['return_mean']:.2f} | {e['strikes']:,}: "
            f"{e['violations/impact']:,}, {e['max_strike_ratio']:.3g} | {e['violations/position']:,} / "
            f"{e['violations/velocity']:,} ({e['max_violation/position']:.3g}, {e['max_violation/velocity']:.3g}) |"
        )
    return "\n".join(lines)
