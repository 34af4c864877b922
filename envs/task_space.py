"""Task-space actions: the policy commands an end-effector displacement; time-scaled IK makes it joint motion.

``TaskSpaceActions(SafetyWrapper(make_planar_reach()))`` (or the Panda). Each control step:

1. ``dr = action * step_size`` [m], ``action in [-1, 1]^k``: the planar arm moves in its x-z plane
   (``k = 2``), the Panda in 3-D (``k = 3``) (``axes``, detected from the joint axes by default).
2. ``J``: the end-effector site's linear Jacobian rows ``axes`` at the current ``q``
   (``ArmReach.ee_jacobian``: MJX's analytic Jacobian of the end-effector site).
3. ``jaxlimits.timescale_ik(J, dr, v_max, t_min=dt, dq_min=q_min - q, dq_max=q_max - q,
   r_norm_max=ee_speed_max)``: the joint displacement ``dq`` and the time ``T >= dt`` that the
   joint velocity limits, the position limits and the end-effector speed cap allow for the whole
   ``dr`` (Suleiman et al. (17)/(21)); the direction of ``dr`` is kept, its speed scaled.
4. ``v_des = dq / T`` (this control step covers ``dt / T`` of the motion), then
   ``a_des = velocity_to_acc(v_des, v, dt)`` (deadbeat tracking), and the inner shield's
   ``step(state, a_des / a_max)``: the viability bounds still guard the joint accelerations, so
   the joint-limit guarantee is the shield's, whatever this layer asks.

Metrics added: ``task/T`` (the ``T`` found [s]), ``task/unreached`` (1.0 when ``dr`` could not be
met: singular ``J`` or the position limits; the least-squares / best-effort motion is used),
``task/tracking_error`` (``||ee_{k+1} - ee_k - (dt / T) J dq||`` [m]: how far the end effector's
move this step is from the planned one; it includes the linearisation, the shield and the tracking
lag), ``task/speed`` (``||ee_{k+1} - ee_k|| / dt`` [m/s]).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxlimits as jl
from jaxlimits.envs.actions import velocity_to_acc
from jaxlimits.envs.arm import ArmReach, State, Wrapper

TASK_METRICS = ("task/T", "task/unreached", "task/tracking_error", "task/speed")


def _base(env) -> ArmReach:
    e = env
    while not isinstance(e, ArmReach):
        if not hasattr(e, "env"):
            raise TypeError(f"TaskSpaceActions needs an ArmReach inside, got {type(env).__name__}")
        e = e.env
    return e


class TaskSpaceActions(Wrapper):
    """Policy actions are end-effector displacements ``action * step_size`` [m]; see the module docstring.

    Args:
      env: a ``SafetyWrapper`` (its ``step`` takes ``a / a_max``; ``limits`` and ``dt`` are read).
      step_size: the displacement [m] commanded by a full action (per axis).
      axes: the site-position components the action moves (default: ``(0, 2)`` for an arm whose
        joints all turn about y, the planar one; ``(0, 1, 2)`` otherwise).
      ee_speed_max: cap on the end-effector speed ``||dr|| / T`` [m/s] (eq. 19, as a norm), or None.
      alpha: ``timescale_ik``'s weight of ``T^2``.
    """

    def __init__(self, env, step_size: float = 0.05, axes=None, ee_speed_max: float | None = None, alpha: float = 1.0):
        super().__init__(env)
        self.base = _base(env)
        self.limits = env.limits
        self.dt = float(env.dt)
        if axes is None:
            ax = np.asarray(self.base.mj_model.jnt_axis)
            axes = (0, 2) if np.allclose(np.abs(ax), [0.0, 1.0, 0.0]) else (0, 1, 2)
        self.axes = tuple(int(a) for a in axes)
        if not self.axes or any(a not in (0, 1, 2) for a in self.axes) or len(set(self.axes)) != len(self.axes):
            raise ValueError(f"axes must be distinct components of (0, 1, 2), got {axes!r}")
        if len(self.axes) > self.base.n:
            raise ValueError(f"{len(self.axes)} task axes need at least as many joints, got {self.base.n}")
        if not step_size > 0:
            raise ValueError(f"step_size must be > 0, got {step_size}")
        if ee_speed_max is not None and not ee_speed_max > 0:
            raise ValueError(f"ee_speed_max must be > 0 or None, got {ee_speed_max}")
        if not alpha > 0:
            raise ValueError(f"alpha must be > 0, got {alpha}")
        self.step_size = float(step_size)
        self.ee_speed_max = None if ee_speed_max is None else float(ee_speed_max)
        self.alpha = float(alpha)
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        self._v_max, self._a_max = f32(self.limits.v_max), f32(self.limits.a_max)
        self._q_min, self._q_max = f32(self.limits.q_min), f32(self.limits.q_max)
        self._idx = jnp.asarray(self.axes)

    @property
    def action_size(self) -> int:
        return len(self.axes)

    def jacobian(self, d):
        """``(k, n)`` linear Jacobian of the end-effector site's ``axes`` at the MJX data ``d`` (a state's
        ``pipeline_state``: its position stage computed)."""
        return self.base.ee_jacobian_at(d)[self._idx, :]

    def plan(self, state: State, action):
        """``(timescale result, dr, J)`` for one unbatched state and action ``(k,)``; ``J`` the ``(k, n)``
        Jacobian at the state the plan was made with."""
        q = state.pipeline_state.qpos
        dr = jnp.asarray(action, jnp.float32) * jnp.float32(self.step_size)
        J = self.jacobian(state.pipeline_state)
        res = jl.timescale_ik(
            J,
            dr,
            self._v_max,
            t_min=self.dt,
            alpha=self.alpha,
            r_norm_max=self.ee_speed_max,
            dq_min=jnp.minimum(self._q_min - q, 0.0),
            dq_max=jnp.maximum(self._q_max - q, 0.0),
        )
        return res, dr, J

    def reset(self, rng) -> State:
        state = self.env.reset(rng)
        zero = jnp.zeros((), jnp.float32)
        return state.replace(metrics=dict(state.metrics, **{k: zero for k in TASK_METRICS}))

    def step(self, state: State, action) -> State:
        res, _, J = self.plan(state, action)
        d = state.pipeline_state
        v_des = res.dq / res.t
        a_des = velocity_to_acc(v_des, d.qvel, self.dt)
        nstate = self.env.step(state, a_des / self._a_max)
        ee0 = d.site_xpos[self.base.ee_site][self._idx]
        ee1 = nstate.pipeline_state.site_xpos[self.base.ee_site][self._idx]
        planned = (self.dt / res.t) * (J @ res.dq)
        metrics = dict(nstate.metrics)
        metrics["task/T"] = res.t
        metrics["task/unreached"] = (~res.reached).astype(jnp.float32)
        metrics["task/tracking_error"] = jnp.linalg.norm(ee1 - ee0 - planned)
        metrics["task/speed"] = jnp.linalg.norm(ee1 - ee0) / self.dt
        return nstate.replace(metrics=metrics)


__all__ = ["TASK_METRICS", "TaskSpaceActions"]
