"""One safety-campaign row: its layout (``make_row``) and the limits its shield claims (``guaranteed``); every
target's rows (the Brax ones in ``campaign``, the Gymnasium ones in ``campaign_gym``) are built here."""

from __future__ import annotations

from jaxlimits.envs.arm import VIOLATION_KEYS


def guaranteed(shield: str, target=None) -> tuple:
    """The limits ``shield`` guarantees on ``target``, of those its env measures: none for ``none``; position,
    velocity, acceleration and torque for every bound method (torque: the arms' ``a_max`` is torque-derived;
    not for ``JointLimitShield`` targets, ``Target.torque_claimed``), jerk for ``jerk``, the impulsive torque for
    ``+impact``. ``target``: a ``campaign.Target`` or ``campaign_gym.GymTarget`` (read: ``measured``,
    ``torque_claimed``), or None (every limit measured, torque claimed)."""
    if shield == "none":
        return ()
    method, *extras = shield.split("+")
    claims = ("position", "velocity", "acceleration") + (("jerk",) if method == "jerk" else ())
    claims += ("torque",) if target is None or target.torque_claimed else ()
    claims += ("impact",) if "impact" in extras else ()
    measured = VIOLATION_KEYS if target is None else target.measured
    return tuple(k for k in claims if k in measured)


def shield_impact(shield: str, point):
    """The impact point ``shield``'s env gets from its target's ``point`` (an ``ImpactPoint`` or None): ``point`` for
    the ``+impact`` shields (the cap enforced), ``point`` measured only (``enforce=False``) for ``none`` (the unshielded
    rows count the strikes over the bound the cap exists for), None for the others."""
    if point is None:
        return None
    method, *extras = shield.split("+")
    if "impact" in extras:
        return point
    return point._replace(enforce=False) if method == "none" else None


def make_row(target, shield: str, policy: str, s: dict, wall: float, compile_s: float) -> dict:
    """One campaign row of (``target``, ``shield``, ``policy``) from the counts ``s``, keyed as
    ``evaluate.summarize``'s row (``env_steps``, ``violations/<k>``, ``max_violation/<k>``,
    ``undisturbed_violations/<k>``, ``nonviable``, ``conflicts``, ``disturbed_steps``, ``impact_infeasible``,
    ``cap_unmet_violations/impact``, ``nonfinite_actions``, ``strikes``); ``wall`` and ``compile_s`` [s]. Every target's ``rows`` builds its rows
    here, so ``format_table``, ``by_shield`` and ``claim_violations`` see one layout."""
    row = {"target": target.name, "shield": shield, "policy": policy, "env_steps": s["env_steps"]}
    row.update(claimed=list(guaranteed(shield, target)), measured=list(target.measured))
    for k in VIOLATION_KEYS:
        row[f"{k}/count"] = s[f"violations/{k}"]
        row[f"{k}/worst"] = s[f"max_violation/{k}"]
        row[f"{k}/undisturbed"] = s[f"undisturbed_violations/{k}"]
    row.update(
        nonviable=s["nonviable"],
        conflicts=s["conflicts"],
        disturbed_steps=s["disturbed_steps"],
        impact_infeasible=s["impact_infeasible"],
        # strikes over the bound whose approach the cap could not bound (outside its claim, counted apart)
        **{"impact/cap_unmet": s["cap_unmet_violations/impact"]},
        nan_substituted=s["nonfinite_actions"],
        strikes=s["strikes"],
        wall_s=round(wall, 2),
        compile_s=round(compile_s, 1),
        env_steps_per_s=round(s["env_steps"] / wall, 1),
    )
    return row
