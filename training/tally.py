"""Count every violation during training: nothing sampled, nothing averaged away.

Training libraries report episode *means* of the metrics, and Brax's ``EpisodeWrapper`` keeps only
the last physics step of an action repeat. To state "zero violations during all of training" we
count them where they happen:

* ``StepTally`` wraps the (unbatched) shielded env, below Brax's training wrappers. Each env step
  it adds the step's ``count/*`` metrics, ``1`` to ``env_steps`` and the non-finite-action count
  to running totals in ``state.info["tally"]`` and keeps the running maximum of ``violation/*``.
  ``info`` survives Brax's auto-reset, so the totals run over the whole of training.
* ``TallyReporter`` wraps the batched env, above Brax's wrappers. After every batched step it sends
  the *increase* of the totals summed over the batch (and the batch maximum) to a host-side
  ``Tally`` through ``jax.debug.callback``: one small host call per batched step.

``wrap_for_training(tally)`` is a drop-in ``wrap_env_fn`` for ``brax.training.agents.*.train``.
PPO's own evaluation env is wrapped the same way, so its steps are counted too (reported apart by
the caller if it wants: ``Tally.env_steps`` counts both).
"""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Wrapper
from brax.envs.wrappers import training as brax_training

from jaxlimits.envs.arm import VIOLATION_KEYS

# "strike": strikes measured (envs with contacts; "count/impact" those over the impulsive-torque bound)
COUNTS = tuple(f"count/{k}" for k in VIOLATION_KEYS) + ("nonfinite_action", "strike", "env_steps")
MAXES = tuple(f"violation/{k}" for k in VIOLATION_KEYS)


class Tally:
    """Host-side totals: violating env-steps per kind, largest magnitudes, env-steps, non-finite actions."""

    def __init__(self):
        self._lock = threading.Lock()
        self.counts = {k: 0 for k in COUNTS}
        self.maxes = {k: 0.0 for k in MAXES}

    def add(self, counts, maxes):
        with self._lock:
            for k, x in counts.items():
                self.counts[k] += int(np.rint(np.sum(np.asarray(x, np.float64))))
            for k, x in maxes.items():
                self.maxes[k] = max(self.maxes[k], float(np.max(x)))

    def state(self) -> dict:
        """The totals as JSON data (a training checkpoint's ``tally``); ``from_state`` reads it back."""
        with self._lock:
            return {"counts": dict(self.counts), "maxes": dict(self.maxes)}

    @classmethod
    def from_state(cls, state: dict) -> "Tally":
        """A ``Tally`` continuing from ``state()`` (a resumed run); raises ``ValueError`` on missing keys."""
        out = cls()
        missing = sorted(set(COUNTS) - set(state.get("counts", {}))) + sorted(set(MAXES) - set(state.get("maxes", {})))
        if missing:
            raise ValueError(f"tally state lacks {missing}")
        out.counts.update({k: int(state["counts"][k]) for k in COUNTS})
        out.maxes.update({k: float(state["maxes"][k]) for k in MAXES})
        return out

    @property
    def env_steps(self) -> int:
        return self.counts["env_steps"]

    def as_dict(self) -> dict:
        out = {
            "env_steps": self.env_steps,
            "nonfinite_actions": self.counts["nonfinite_action"],
            "strikes": self.counts["strike"],
        }
        for k in VIOLATION_KEYS:
            out[f"violations/{k}"] = self.counts[f"count/{k}"]
            out[f"max_violation/{k}"] = self.maxes[f"violation/{k}"]
        return out


class StepTally(Wrapper):
    """Running totals of one env's violations in ``state.info["tally"]`` (see the module doc)."""

    def reset(self, rng):
        state = self.env.reset(rng)
        zero = jnp.zeros((), jnp.float32)
        state.info["tally"] = {k: zero for k in COUNTS + MAXES}
        return state

    def step(self, state, action):
        tally = state.info["tally"]
        state = self.env.step(state, action)
        m = state.metrics
        new = {k: tally[k] + m.get(k, 0.0) for k in COUNTS if k != "env_steps"}
        new["env_steps"] = tally["env_steps"] + 1.0
        new.update({k: jnp.maximum(tally[k], m[k]) for k in MAXES})
        state.info["tally"] = new
        return state


class TallyReporter(Wrapper):
    """Report the batch's increase of the ``StepTally`` totals to a host ``Tally`` each step."""

    def __init__(self, env, tally: Tally):
        super().__init__(env)
        self._tally = tally

    def step(self, state, action):
        before = state.info["tally"]
        state = self.env.step(state, action)
        after = state.info["tally"]
        counts = {k: jnp.sum(after[k] - before[k]) for k in COUNTS}
        maxes = {k: jnp.max(after[k]) for k in MAXES}
        jax.debug.callback(self._tally.add, counts, maxes)
        return state


def wrap_for_training(tally: Tally):
    """A ``wrap_env_fn`` for Brax's trainers: ``StepTally`` below, ``TallyReporter`` above ``training.wrap``."""

    def wrap(env, episode_length=1000, action_repeat=1, randomization_fn=None):
        if randomization_fn is not None:
            # Brax's DomainRandomizationVmapWrapper steps ``env.unwrapped`` directly, past every wrapper in between
            # (``StepTally`` and Brax's own ``EpisodeWrapper``): the tally would count nothing, silently
            raise ValueError(
                "tally.wrap_for_training cannot count under a randomization_fn: Brax's DomainRandomizationVmapWrapper"
                " steps the innermost env past StepTally; count from the shield's state.metrics['shield/*'] instead"
            )
        inner = brax_training.wrap(StepTally(env), episode_length=episode_length, action_repeat=action_repeat)
        return TallyReporter(inner, tally)

    return wrap
