"""A wall-strike *task* over any robot MJCF (Brax ``PipelineEnv``, MJX backend): reach a wall ahead and press it.

    env = Strike(ASSETS / "planar3.xml", home=PLANAR_HOME)                  # the planar arm
    env = JointLimitShield(env, impact=strike_point(env))                   # the one shield, its strikes capped

``WallStrike``'s task (``envs/wall_strike.py``) without its physics: the scene is the robot's MJCF plus a ball at its
site ``ee`` and a wall (``wall_strike.wall_xml``: only the two collide), and the physics is the model's own, one
``pipeline_step`` per control step, so that ``JointLimitShield`` takes it over as for any Brax env: the bounds, the
impact cap (``ImpactPoint``) and the strikes' measurement (``envs/strike_record.py``, at every substep) are the one
shield's, not the task's. The wall lies along a known ``normal`` (unit, from the robot into the wall) at a distance drawn
per episode (``gap`` ahead of the ball's surface, uniform in ``[gap_low, gap_high]``).

Actions as ``Reach``'s (``action="acceleration"`` by default: joint accelerations scaled by the MJCF's
``jaxlimits_a_max``). Reward ``-distance`` to the wall, ``+ contact_bonus`` when the ball touches it at the step's end,
and the normal impulse the wall takes over the step, ``dt`` times the ball's contact force at the step's end, clipped
to ``impulse_limit`` [N s] (``WallStrike`` sums it over the substeps, which the task no longer sees). ``metrics``:
``distance``, ``contact``, ``impulse``, ``success`` (1.0 once the ball touched the wall at a step's end in the
episode; restarted at every episode's first step, ``time == 0``: also after Brax's auto-reset, which restores the
reset's physics state but not ``info``). Episodes do not terminate.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxlimits.envs.arm import _mjx_tracing
from jaxlimits.envs.impact_point import ImpactPoint
from jaxlimits.envs.reach import ASSETS, Reach, State
from jaxlimits.envs.wall_strike import PLANAR_HOME, PLANAR_WALL, _quat_z_to, check_wall_task, wall_xml


class Strike(Reach):
    """Strike and press a wall ahead of the robot's site ``ee`` (module docstring).

    Args:
      xml_path: the robot's MJCF (``Reach``'s conventions, a site ``ee``). home: ``(n,)`` start posture [rad or m].
      normal: ``(3,)`` strike direction (the wall's normal points back at the robot). gap_low, gap_high: the wall's
        distance ahead of the ball's surface at reset, uniform [m]. q_noise: starts are ``home`` + U(-q_noise,
        q_noise) [rad or m].
      ball_radius, solref, friction: the ball-wall contact (``wall_xml``). contact_bonus, impulse_limit: reward terms.
      c_range, dt_impact: the impact model of ``strike_point`` (restitution range, impact duration [s]).
      **kwargs: ``Reach``'s (``n_frames``, ``action``, ``acceleration_scale``).
    """

    def __init__(
        self,
        xml_path,
        home,
        normal=(1.0, 0.0, 0.0),
        gap_low: float = 0.005,
        gap_high: float = 0.05,
        q_noise: float = 0.1,
        ball_radius: float = 0.02,
        solref=(0.004, 1.0),
        friction: float = 1.0,
        contact_bonus: float = 1.0,
        impulse_limit: float = 2.0,
        c_range=(0.0, 0.2),
        dt_impact: float = 0.005,
        **kwargs,
    ):
        scene = wall_xml(float(ball_radius), tuple(float(x) for x in solref), float(friction), str(xml_path))
        super().__init__(scene, **{"action": "acceleration", **kwargs})
        mjm = self.mj_model
        self.home, self.normal, self.gap = check_wall_task("Strike", mjm.nq, home, normal, gap_low, gap_high)
        for field, value in (("q_noise", q_noise), ("contact_bonus", contact_bonus), ("impulse_limit", impulse_limit)):
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"Strike: {field} must be a finite number >= 0, got {value!r}")
        self.q_noise = float(q_noise)
        self.ball_radius = float(ball_radius)
        self.friction = float(friction)
        self.contact_bonus, self.impulse_limit = float(contact_bonus), float(impulse_limit)
        self.c_range, self.dt_impact = tuple(float(c) for c in c_range), float(dt_impact)
        self._wall_quat = jnp.asarray(_quat_z_to(-self.normal), jnp.float32)
        self._dt = float(mjm.opt.timestep) * self._n_frames

    @property
    def observation_size(self) -> int:
        return 3 * self.sys.nq + 7

    @_mjx_tracing
    def reset(self, rng: jax.Array) -> State:
        k_q, k_g = jax.random.split(rng)
        n = self.sys.nq
        q = jnp.asarray(self.home, jnp.float32) + jax.random.uniform(
            k_q, (n,), jnp.float32, -self.q_noise, self.q_noise
        )
        gap = jax.random.uniform(k_g, (), jnp.float32, *self.gap)
        nrm = jnp.asarray(self.normal, jnp.float32)
        wall = self._ee(q) + (self.ball_radius + gap) * nrm
        ft = jnp.result_type(float)  # the physics' dtype (float64 under jax_enable_x64)
        ps = self.pipeline_init(q.astype(ft), jnp.zeros(self.sys.nv, ft))
        # the wall's mocap pose: the next step's first substep collides at it (its position stage comes first)
        ps = ps.replace(mocap_pos=wall[None].astype(ft), mocap_quat=self._wall_quat[None].astype(ft))
        zero = jnp.zeros((), jnp.float32)
        dist = self._distance(ps, wall)
        metrics = {"distance": dist, "contact": zero, "impulse": zero, "success": zero}
        info = {"wall": wall, "struck": zero}
        return State(ps, self._obs(ps, wall), -dist, zero, metrics, info)

    def _distance(self, ps, wall):
        """``()`` the ball's gap to the wall along ``normal`` [m], 0 in contact."""
        ee = ps.site_xpos[self._site]
        return jnp.maximum(jnp.dot(wall - ee, jnp.asarray(self.normal, ee.dtype)) - self.ball_radius, 0.0)

    def _press(self, ps):
        """``(touch, force)``: the ball touches the wall at the step's last substep, and the contact's normal force [N]
        (the sum of its rows' forces: the normal force of a frictionless or pyramidal contact, MJX's cone)."""
        impl = ps._impl if hasattr(ps, "_impl") else ps
        if impl.ncon == 0 or impl.efc_J.shape[0] == 0:
            zero = jnp.zeros((), jnp.float32)
            return zero, zero
        touch = jnp.any(impl.contact.dist < impl.contact.includemargin).astype(jnp.float32)
        rows = impl.efc_type >= int(mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS)
        return touch, jnp.sum(jnp.where(rows, impl.efc_force, 0.0)).astype(jnp.float32)

    @_mjx_tracing
    def step(self, state: State, action: jax.Array) -> State:
        ps0 = state.pipeline_state
        ps = self.pipeline_step(ps0, self.ctrl(ps0, action))
        wall = state.info["wall"]
        dist = self._distance(ps, wall)
        touch, force = self._press(ps)
        impulse = jnp.minimum(force * self._dt, self.impulse_limit)
        struck = jnp.maximum(jnp.where(ps0.time == 0, 0.0, state.info["struck"]), touch)
        reward = -dist + self.contact_bonus * touch + impulse
        metrics = dict(state.metrics, distance=dist, contact=touch, impulse=impulse, success=struck)
        info = dict(state.info, struck=struck)
        return state.replace(pipeline_state=ps, obs=self._obs(ps, wall), reward=reward, metrics=metrics, info=info)

    def _obs(self, ps, wall):
        ee = ps.site_xpos[self._site]
        dist = jnp.dot(wall - ee, jnp.asarray(self.normal, ee.dtype))[None] - self.ball_radius
        parts = [jnp.cos(ps.qpos), jnp.sin(ps.qpos), ps.qvel, ee, wall - ee, dist]
        return jnp.concatenate(parts).astype(jnp.float32)


def strike_point(env: Strike, **kwargs) -> ImpactPoint:
    """The ``ImpactPoint`` of ``env``'s strikes for ``JointLimitShield(impact=)``: the site ``ee`` (the ball's centre)
    along ``env.normal``, ``env``'s restitution range and impact duration, the ball-wall contact's friction
    (``CoulombContact``), the impulsive torque bound the motors' peak torque (``ImpactPoint``'s default, as
    ``WallStrike``'s); ``kwargs`` override fields. No ``surface``: the wall's place changes per episode, so the cap
    applies everywhere (as ``SafetyWrapper(impact=True)`` on ``WallStrike``)."""
    import jaxlimits.impact as _impact

    fields = dict(
        normal=tuple(env.normal),
        c_range=env.c_range,
        dt_impact=env.dt_impact,
        contact=_impact.CoulombContact(env.friction),
    )
    return ImpactPoint("ee", **{**fields, **kwargs})


def make_planar_robot_wall(**kwargs) -> Strike:
    """The planar 3-link arm's wall strike (``WallStrike``'s ``PLANAR_WALL``: the wall 5-25 cm ahead along +x,
    frictionless, restitution up to 0.4) as a task over the robot, for the one shield."""
    fields = {k: v for k, v in PLANAR_WALL.items() if k not in ("arm", "home")}
    return Strike(ASSETS / "planar3.xml", PLANAR_HOME, **{**fields, **kwargs})


__all__ = ["Strike", "make_planar_robot_wall", "strike_point"]
