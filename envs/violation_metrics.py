"""``ViolationMetrics``: a ``JointLimitShield``'s per-step record under the metric names the project's
trainers, tallies and evaluator read (``jaxlimits.training.tally``, ``jaxlimits.training.evaluate``).

Per step, for every ``VIOLATION_KEYS`` kind: ``count/<kind>`` (1.0 when the step's excess is positive) and
``violation/<kind>`` (the excess, from ``state.info["violation"]``; ``acceleration``, which ``JointLimitShield`` does
not measure, is 0, so are ``jerk`` where the robot has no ``j_max`` and ``impact`` without an impact point); and
``intervention``, ``viable``,
``nonfinite_action``, ``torque_box_conflict``, ``disturbance`` from the shield's ``shield/intervention``,
``shield/nonviable``, ``shield/nonfinite``, ``shield/torque_conflict``, ``shield/disturbance``; with an impact point (``JointLimitShield(
impact=)``) ``impact_cap``, ``impact_infeasible``, ``strike``, ``strike_ratio`` (``SafetyWrapper``'s and
``WallStrike``'s names) and ``strike_cap_unmet`` from ``shield/impact_cap``, ``shield/impact_infeasible``,
``shield/strike``, ``shield/strike_ratio`` and ``shield/strike_cap_unmet``. Nothing else changes.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits.envs.arm import VIOLATION_KEYS, State, Wrapper

_RENAMED = {
    "disturbance": "shield/disturbance",  # a contact pushed a shielded joint (the evaluator's disturbed steps)
    "intervention": "shield/intervention",
    "nonfinite_action": "shield/nonfinite",
    "torque_box_conflict": "shield/torque_conflict",
}


def _with_metrics(state: State) -> State:
    viol = state.info["violation"]
    metrics = dict(state.metrics)
    zero = jnp.zeros((), jnp.float32)
    for k in VIOLATION_KEYS:
        x = jnp.asarray(viol.get(k, zero), jnp.float32)
        metrics[f"count/{k}"] = (x > 0).astype(jnp.float32)
        metrics[f"violation/{k}"] = x
    for name, source in _RENAMED.items():
        metrics[name] = jnp.asarray(state.metrics[source], jnp.float32)
    metrics["viable"] = 1.0 - jnp.asarray(state.metrics["shield/nonviable"], jnp.float32)
    for name in ("impact_cap", "impact_infeasible", "strike", "strike_ratio", "strike_cap_unmet"):
        if f"shield/{name}" in state.metrics:
            metrics[name] = jnp.asarray(state.metrics[f"shield/{name}"], jnp.float32)
    return state.replace(metrics=metrics)


class ViolationMetrics(Wrapper):
    """Wraps a ``JointLimitShield`` (or a wrapper of one); see the module docstring."""

    def reset(self, rng) -> State:
        return _with_metrics(self.env.reset(rng))

    def step(self, state: State, action) -> State:
        return _with_metrics(self.env.step(state, action))
