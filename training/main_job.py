"""The main job (``make demo``): both guarantees trained and measured, one table.

``run(out, cfg, contact_cfg=...)`` runs two tasks, each trained from the same config and seed per
shield and evaluated over ``eval_episodes`` parallel episodes (``evaluate.Evaluator``):

- ``reach`` (``cfg``, planar reach; ``jaxlimits main``'s default ``planar_robot_reach_ppo``: the planar arm
  as a robot, ``JointLimitShield`` over ``Reach(action="acceleration")``): one run per shield (default
  ``viability`` and ``none``); with velocity actions and the IK observation also
  ``evaluate.ik_reference_policy`` (a greedy scripted reach controller, viability shield, same episodes),
  the reference a learned policy is measured against;
- ``contact`` (``contact_cfg``, the planar wall strike; ``contact_job``): the joint-limit shield with
  and without the impact-aware speed cap, every strike measured and counted.

Either task can be left out (``cfg=None`` / ``contact_cfg=None``). It prints one comparison table
(``experiment.format_table``) and writes to ``out``: ``runs/<shield>/`` (reach runs),
``contact/runs/<variant>/`` (contact runs), ``results.json`` (the reach section at the top level as
before, ``"contact"``: the contact job's results), ``results.md`` (the table),
``training_curves.png`` and ``contact_curves.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

from jaxlimits.training import brax_ppo, contact_job, evaluate, experiment
from jaxlimits.training.config import RunConfig


def run(
    out,
    cfg: RunConfig | None,
    shields=("viability", "none"),
    show_progress: bool = True,
    contact_cfg: RunConfig | None = None,
    contact_variants=tuple(contact_job.VARIANTS),
) -> dict:
    if cfg is None and contact_cfg is None:
        raise ValueError("the main job needs at least one task: cfg (reach) or contact_cfg (contact)")
    out = Path(out)
    t0 = time.perf_counter()
    results, sections, curves = {}, {}, {}
    if cfg is not None:
        results.update(config=cfg.to_dict(), shields={})
        runs = {}
        for shield in shields:
            runs[shield] = out / "runs" / shield
            results["shields"][shield] = experiment.train_and_evaluate(
                cfg.override(shield=shield), runs[shield], show_progress
            )
        if cfg.action_mode == "velocity" and cfg.ik_observation:
            env = brax_ppo.env_from_config(cfg.override(shield="viability"))
            policy = evaluate.ik_reference_policy(env.action_size, env.limits.v_max)
            results["reference"] = evaluate.evaluate(
                env, policy, None, episodes=cfg.eval_episodes, episode_length=cfg.episode_length, seed=cfg.seed + 1
            )
        sections["reach"] = {"runs": results["shields"], "reference": results.get("reference")}
        curves["training_curves.png"] = ("reach", runs)
    if contact_cfg is not None:
        results["contact"] = contact_job.run(out / "contact", contact_cfg, show_progress, contact_variants, quiet=True)
        sections["contact"] = {"runs": results["contact"]["variants"]}
        curves["contact_curves.png"] = ("contact", contact_job.run_folders(out / "contact", contact_variants))
    results["wall_s"] = time.perf_counter() - t0
    experiment.write_results(out, results, experiment.format_table(sections), curves)
    return results
