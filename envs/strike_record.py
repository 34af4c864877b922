"""One strike measured from the physics, substep by substep: the impulsive joint torque of its contact impulse.

Wang & Kheddar 2019 bound the impulsive joint torque of an impact, ``tau_imp = J^T F = J^T p / dt_impact`` (20),
``p`` the contact impulse over the impact's duration ``dt_impact``. The simulator has no impact event, only contact
forces per substep, so a *strike* is measured as a window:

* it opens at the first substep in which the striking geometry is in contact (``in_contact``), storing the joint
  position and velocity before that substep (``q_pre``, ``v_pre``) and the point's approach speed ``w`` [m/s];
* it closes when the approach speed has dropped below ``stop_fraction`` of ``w`` (the compression phase: the rigid
  model's impact), at most ``window_substeps`` substeps after it opened;
* over it the contact's joint impulse ``impulse = sum(joint_force h)`` [N m s] is accumulated.

The strike is counted once, in the control step its window closes (``finish``): ``ratio = max_j |impulse_j| /
dt_impact / tau_imp_max_j`` (the measured impulsive torque over its bound; > 1 is a violation, its excess
``ratio - 1``). The record re-arms once a strike's window has closed and the geometry was off contact for a whole
control step (``off``), so that every strike is measured, re-strikes after a bounce or a pull-back too, and it starts
afresh at every episode's first step. ``struck`` (kept across re-arms) says whether the episode struck at all.

The impact cap's claim covers a strike only where the cap was delivered: the approach speed at the first contact is
set by the control step it falls in and the one before (a constant acceleration over each). The cap is not delivered
where the shield could not meet it (its joint-limit bounds win over the cap, which is then met with least violation
and flagged: a caller with a cap passes each step's ``cap_unmet`` to ``advance`` and ``finish``) or where the
actuators could not realise the decided acceleration (a substep whose actuators saturated: ``advance``'s
``saturated``; the realised approach is then not the one the cap bounded). The record keeps whether the current step
saturated before the current substep (``sat_step``, cleared by ``finish``) and whether the previous step did not
deliver its cap (``unmet_prev``, kept across re-arms like ``struck``), stores at the window's first substep whether
the cap was not delivered in that step (before the first contact) or the one before (``unmet``) and gives it with the
strike (``finish``'s ``cap_unmet``): a strike over its bound there is the documented outcome of an undelivered cap,
counted apart from the claim's violations.

The record is a flat dict of float32 arrays (a pytree: it lives in a Brax ``State.info``). Every function takes the
array module ``xp`` (``jax.numpy``, the default, or ``numpy``). Used by ``WallStrike`` (which adds its own fields), by
``JointLimitShield(impact=ImpactPoint(...))`` and by ``JointLimitShieldWrapper(impact=...)`` (numpy, C MuJoCo), whose
``info["violation"]["impact"]`` it gives.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def fresh(n: int, xp=jnp) -> dict:
    """An armed record for ``n`` joints (no strike measured yet); ``struck`` (whether the episode struck before) 0:
    ``start_step`` keeps it across re-arms."""
    f32 = np.float32
    zero = xp.zeros((), f32)
    zn = xp.zeros((n,), f32)
    return {
        "struck": zero,
        "hit": zero,  # 1 once the window opened
        "off": xp.ones((), f32),  # 1: the last control step had no substep in contact
        "k": zero,  # substeps in the window so far
        "open": xp.ones((), f32),  # 1 until the window has closed
        "w": zero,  # approach speed at the window's first substep [m/s]
        "q_pre": zn,
        "v_pre": zn,
        "impulse": zn,  # contact joint impulse over the window [N m s]
        "unmet": zero,  # 1: the cap was not delivered in the step the window opened in or the one before
        "unmet_prev": zero,  # 1: the last control step's cap was not delivered (kept across re-arms)
        "sat_step": zero,  # 1: an actuator saturated in this control step before the current substep
    }


def start_step(kept: dict, fresh_record: dict, first_step, xp=jnp) -> dict:
    """The record a control step starts from: ``fresh_record`` (``fresh``'s fields and those a caller adds) at an
    episode's first step (``first_step``, a bool ``()``) or once ``kept``'s strike has closed and a whole step passed
    off contact, else ``kept``; ``struck`` and ``unmet_prev`` are 0 at an episode's first step, else ``kept``'s (kept
    across re-arms)."""
    new = first_step | ((kept["hit"] > 0) & (kept["open"] == 0) & (kept["off"] > 0))
    record = {k: xp.where(new, fresh_record[k], kept[k]) for k in fresh_record}
    for k in ("struck", "unmet_prev"):
        record[k] = xp.where(first_step, 0.0, kept[k]).astype(np.float32)
    return record


def in_strike(record: dict, in_contact):
    """Whether a substep with ``in_contact`` (bool ``()``) belongs to a strike: its first substep (no window opened
    yet) or one in its open window. There the velocity jump is the impact cap's to bound: a shield holding the
    realised acceleration in its bounds against the contact would push the point on into the surface."""
    return in_contact & ((record["hit"] == 0) | (record["open"] > 0))


def advance(
    rec: dict,
    in_contact,
    w_pre,
    w_post,
    q,
    v,
    joint_force,
    h,
    window_substeps: int,
    stop_fraction: float,
    xp=jnp,
    cap_unmet=False,
    saturated=False,
):
    """``(rec, in_window)``: the record after one substep.

    in_contact: ``()`` bool, the striking geometry touches in this substep. w_pre, w_post: ``()`` the point's
    approach speed [m/s] before and after the substep. q, v: ``(n,)`` joint position and velocity before it.
    joint_force: ``(n,)`` the contact's joint force in it [N m]. h: the substep [s]. cap_unmet: ``()`` bool, this
    control step's impact cap could not be met (False without a cap). saturated: ``()`` bool, an actuator saturated
    in this substep (its realised acceleration is not the decided one; it counts for strikes from the next substep
    on, this substep's own approach speed ``w_pre`` being set before it). ``in_window``: ``()`` bool, this substep was
    inside the window (callers accumulate their own fields over it)."""
    f32 = np.float32
    first = (rec["hit"] == 0) & in_contact
    hit = xp.where(in_contact, 1.0, rec["hit"]).astype(f32)
    w_hit = xp.where(first, w_pre, rec["w"]).astype(f32)
    stopped = (hit > 0) & (w_post <= stop_fraction * w_hit)
    in_window = (hit > 0) & (rec["open"] > 0)
    closes = in_window & (stopped | (rec["k"] + 1 >= window_substeps))
    undelivered = xp.maximum(xp.maximum(rec["unmet_prev"], rec["sat_step"]), xp.asarray(cap_unmet, f32))
    new = dict(rec)
    new.update(
        struck=xp.maximum(rec["struck"], hit),
        hit=hit,
        k=(rec["k"] + in_window).astype(f32),
        open=xp.where(closes, 0.0, rec["open"]).astype(f32),
        w=w_hit,
        q_pre=xp.where(first, q, rec["q_pre"]).astype(f32),
        v_pre=xp.where(first, v, rec["v_pre"]).astype(f32),
        unmet=xp.where(first, undelivered, rec["unmet"]).astype(f32),
        sat_step=xp.maximum(rec["sat_step"], xp.asarray(saturated, f32)),
        impulse=(rec["impulse"] + xp.where(in_window, joint_force * h, 0.0)).astype(f32),
    )
    return new, in_window


def impulsive_ratio(impulse, dt_impact: float, tau_imp_max, xp=jnp):
    """``()`` ``max_j |impulse_j| / dt_impact / tau_imp_max_j``: the measured impulsive torque over its bound (20)."""
    return xp.max(xp.abs(impulse) / np.float32(dt_impact) / xp.asarray(tau_imp_max, np.float32))


def finish(start: dict, end: dict, contact_in_step, dt_impact: float, tau_imp_max, xp=jnp, cap_unmet=False):
    """``(record, strike)`` at a control step's end: ``record`` with ``off`` set (``contact_in_step``: any substep of
    the step in contact), ``unmet_prev`` (this step's cap not delivered: ``cap_unmet``, it could not be met, or an
    actuator saturated in one of the step's substeps) and ``sat_step`` cleared, and ``strike``
    ``{"strike": 1.0 in the step the window closed, "ratio": its impulsive ratio then (else 0), "excess": max(ratio -
    1, 0) then, "speed": its approach speed w then [m/s], "cap_unmet": 1.0 then if the cap was not delivered in the step
    the window opened in or the one before}`` (float32 ``()`` each)."""
    f32 = np.float32
    closed = (start["open"] > 0) & (end["open"] == 0)
    ratio = xp.where(closed, impulsive_ratio(end["impulse"], dt_impact, tau_imp_max, xp), 0.0).astype(f32)
    undelivered = xp.maximum(xp.asarray(cap_unmet, f32), end["sat_step"])
    record = dict(
        end,
        off=(1.0 - xp.asarray(contact_in_step, f32)),
        unmet_prev=undelivered,
        sat_step=xp.zeros_like(end["sat_step"]),
    )
    strike = {
        "strike": xp.asarray(closed, f32),
        "ratio": ratio,
        "excess": xp.maximum(ratio - f32(1.0), f32(0.0)),
        "speed": xp.where(closed, end["w"], 0.0).astype(f32),
        "cap_unmet": xp.where(closed, end["unmet"], 0.0).astype(f32),
    }
    return record, strike


__all__ = ["advance", "finish", "fresh", "impulsive_ratio", "in_strike", "start_step"]
