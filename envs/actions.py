"""Action parametrisations on top of a shielded arm env: what the policy's ``[-1, 1]^n`` means.

The shield always works on joint *accelerations* (``SafetyWrapper.step`` takes ``action * a_max``).
A policy may be easier to learn with another meaning of its action; these wrappers translate it
into an acceleration command *before* the shield, so the guarantee is unchanged:

* ``"acceleration"`` (no wrapper): ``a_des = action * a_max`` [rad/s^2].
* ``"velocity"`` (``VelocityActions``): ``v_des = action * v_max`` [rad/s], tracked deadbeat:
  ``a_des = (v_des - v) / dt`` (``velocity_to_acc``), i.e. the acceleration that would reach
  ``v_des`` at the end of the control step under the semi-implicit model (``v+ = v + dt a``). The
  shield then projects it into the safe interval, so far from ``v_des`` the arm accelerates as hard
  as the bounds allow and near it arrives exactly. Without a shield (``method="none"``) the raw
  command, up to ``2 v_max / dt``, is applied (and the motors saturate: counted).
* ``"task_space"`` (``jaxlimits.envs.task_space.TaskSpaceActions``, default options): an
  end-effector displacement, turned into joint motion by time-scaled IK (Suleiman et al.), then
  tracked like ``"velocity"``.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits.envs.arm import State, Wrapper

ACTION_MODES = ("acceleration", "velocity", "task_space")


def velocity_to_acc(v_des, v, dt):
    """Deadbeat velocity tracking: the acceleration ``(v_des - v) / dt`` [rad/s^2], shapes ``(..., n)``.

    ``dt`` is the control period [s] (a positive Python float). Non-finite ``v_des`` gives a
    non-finite command, which the shield replaces by braking (and counts).
    """
    return (jnp.asarray(v_des, jnp.float32) - v) / jnp.float32(dt)


class VelocityActions(Wrapper):
    """Policy actions are joint velocity commands ``action * v_max``; see the module docstring.

    Wraps a ``SafetyWrapper`` (or anything whose ``step`` takes ``a / a_max`` and whose
    ``pipeline_state.qvel`` is the joint velocity); ``env.limits`` and ``env.dt`` are read from it.
    """

    def __init__(self, env):
        super().__init__(env)
        self.limits = env.limits
        self.dt = float(env.dt)
        self._v_max = jnp.asarray(self.limits.v_max, jnp.float32)
        self._a_max = jnp.asarray(self.limits.a_max, jnp.float32)

    def step(self, state: State, action) -> State:
        v_des = jnp.asarray(action, jnp.float32) * self._v_max
        a_des = velocity_to_acc(v_des, state.pipeline_state.qvel, self.dt)
        return self.env.step(state, a_des / self._a_max)


def with_action_mode(env, mode: str):
    """``env`` (a shielded env) with the policy's actions meaning ``mode`` (one of ``ACTION_MODES``)."""
    if mode not in ACTION_MODES:
        raise ValueError(f"action mode must be one of {ACTION_MODES}, got {mode!r}")
    if mode == "task_space":
        from jaxlimits.envs.task_space import TaskSpaceActions  # imports this module

        return TaskSpaceActions(env)
    return VelocityActions(env) if mode == "velocity" else env


__all__ = ["ACTION_MODES", "VelocityActions", "velocity_to_acc", "with_action_mode"]
