"""Wall strike (MJX): reach and press a wall whose position along a known normal is uncertain.

Two arms: the Panda (``make_wall_strike``, ``assets/panda.xml``) and the planar 3-link arm
(``make_planar_wall_strike``, ``assets/planar3.xml``: fast enough to *train* on a CPU). The scene is
the arm's MJCF plus, built with ``mujoco.MjSpec`` (no copy of the arm's MJCF): a collision sphere at
the end-effector site (``ee_ball``, radius ``ball_radius``) and a wall, a plane on a mocap body whose
normal faces the robot. The strike direction ``normal`` (unit, from the robot
into the wall) is known; the wall's distance along it is drawn per episode
(``gap`` in ``[gap_low, gap_high]`` ahead of the ball). Only the ball and the wall collide; the
joint-limit constraint stays disabled (overshoot is measured, as in ``ArmReach``).

Actions are joint accelerations realised by inverse dynamics without contact forces (``ArmReach``);
the constraint solver then adds the contact force, so *during contact the realised acceleration
differs from the command* (``metrics['accel_error']`` measures it; it is 0 to roundoff before the
first contact).

Impact measurement (per strike, ``info['impact']``, from the MJX contact forces): at the first
substep whose contact is active (penetration ``dist < 0``) the pre-impact joint velocity ``v_pre``,
the position ``q_pre`` and the contact-normal velocity ``w`` (finite difference of the sphere's
centre over the previous substep, ``normal`` component) are stored. The impact window runs from
there until the ball's normal velocity has dropped below ``stop_fraction`` (10 %) of ``w`` (the
compression phase, the rigid model's impact), at most ``window`` seconds; with ``solref[0] = 2 h``
it is one 2 ms substep in practice. Over it the contact joint impulse ``sum(qfrc_constraint) h``
(``impulse``) and the joint momentum change ``sum(qfrc_constraint + qfrc_actuator - h) h``
(``momentum``, = ``M dq`` of the rigid model) [N m s] are accumulated. ``metrics``: ``impact/hit``
(1 once hit), ``impact/w`` [m/s], ``impact/tau`` = ``max_j |momentum_j| / dt_impact /
tau_imp_max_j`` (the measured impulsive torque over its bound; the rigid model's ``dtau = M dq /
dt_impact`` is the same quantity), ``impact/tau_contact`` (the same with the contact impulse alone),
``impact/v_post`` = ``max_j max_{t >= impact} |qvel_j| / v_max_j``; a ratio > 1 is a violation.
Each strike is counted once, in the step its window closes: ``strike`` (1.0 then), ``strike_ratio``
(its ``impact/tau_contact``), ``strike_cap_unmet`` (1.0 then if the shield's cap was not delivered in the step
the strike began in, before its contact, or the one before: ``step_acc``'s ``cap_unmet``, or a substep's motors
saturated; outside the cap's claim), and the violation metrics ``count/impact`` / ``violation/impact`` (the
ratio's excess over 1), which ``training/tally.py`` and the evaluator count like every limit. The
record restarts at every episode's first step (``time == 0``: also after Brax's auto-reset, which
restores the reset's physics state but not ``info``), and re-arms within an episode once a strike's
window has closed and the ball has been off the wall for a whole control step (``off``), so that every
strike is measured: bounces and re-strikes after a pull-back too. ``success`` is 1.0 once the wall was
struck in the episode (``struck``, kept across re-arms).

Reward: ``-distance`` to the wall before contact, ``+ contact_bonus`` per step in contact, and the
normal impulse delivered in the step, clipped to ``impulse_limit`` [N s] per step.
"""

from __future__ import annotations

import functools
import itertools
import pathlib
import tempfile
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxlimits.envs import mjx_stages, strike_record

import jaxlimits.impact as _impact
from jaxlimits.envs.actuation import contact_correction
from jaxlimits.envs.arm import ASSETS, VIOLATION_KEYS, ArmReach, State, _mjx_tracing

HOME = np.array([0.0, 0.0, 0.0, -1.57079, 0.0, 1.57079, -0.7853])
# planar 3-link arm (vertical x-z plane): end effector at (0.29, 0, -0.66), moving along +x well
# conditioned (every link has a lever arm on it)
PLANAR_HOME = np.array([0.6, 1.0, 0.8])


class ImpactSpec(NamedTuple):
    """The impact model's parameters and bounds (units SI).

    c_range: restitution range ``(c_min, c_max)``; the predictions use ``c_max`` (worst case).
    dt_impact: impact duration [s] (the paper's 0.005 s), distinct from the control step.
    tau_imp_max: (n,) impulsive joint torque bound [N m].
    window: measurement window after the first contact [s].
    contact: the contact model of the predictions (``jaxlimits.impact.CoulombContact(mu)`` with the
      ball-wall friction by default: the contact the simulator has).
    """

    c_range: tuple
    dt_impact: float
    tau_imp_max: np.ndarray
    window: float
    contact: _impact.ContactModel


@functools.lru_cache(maxsize=8)
def wall_xml(
    ball_radius: float = 0.02,
    solref=(0.004, 1.0),
    friction: float = 1.0,
    arm: str = "panda.xml",
    solver_iterations: int = 4,
    ls_iterations: int = 8,
) -> str:
    """Path of the generated scene MJCF (``assets/<arm>`` + ``ee_ball`` at its site ``ee`` + mocap wall),
    cached per process; the file lives in a temporary folder removed at the interpreter's exit.

    ``solver_iterations`` / ``ls_iterations``: the constraint solver's caps (MuJoCo's defaults are 100 /
    50). MuJoCo stops at its tolerance, but under ``vmap`` MJX's solver loop runs until the *whole batch*
    has converged, in float32 often to the cap: one frictionless ball-wall contact converges in a Newton
    step or two. Measured on the planar wall strike (256 episodes x 100 steps, trained policies): 4 / 8
    runs 2.3x faster than 100 / 50 with the same strikes (worst impulsive-torque ratio equal to 7
    digits) and joint velocities within 1e-4 rad/s; 1 / 4 is off by 1.3 rad/s.
    """
    spec = mujoco.MjSpec.from_file(str(ASSETS / arm))
    spec.option.iterations, spec.option.ls_iterations = int(solver_iterations), int(ls_iterations)
    site = spec.site("ee")
    if site is None:
        raise ValueError(f"{arm}: no site named 'ee' (the ball is placed there)")
    ball = site.parent.add_geom()
    ball.name, ball.type, ball.size = "ee_ball", mujoco.mjtGeom.mjGEOM_SPHERE, [ball_radius, 0, 0]
    ball.pos = list(site.pos)
    # friction 0: a frictionless contact (condim 1, the normal force only: what the impact model predicts)
    ball.contype, ball.conaffinity, ball.mass, ball.condim = 1, 1, 0.0, 3 if friction > 0 else 1
    ball.solref, ball.friction = list(solref), [friction, 0.005, 0.0001]
    wall = spec.worldbody.add_body()
    wall.name, wall.mocap = "wall", True
    g = wall.add_geom()
    g.name, g.type, g.size = "wall", mujoco.mjtGeom.mjGEOM_PLANE, [0.6, 0.6, 0.01]
    g.contype, g.conaffinity, g.solref, g.friction = 1, 1, list(solref), [friction, 0.005, 0.0001]
    g.condim = ball.condim
    g.rgba = [0.3, 0.5, 0.8, 0.5]
    spec.compile()
    path = pathlib.Path(_scene_dir().name) / f"{pathlib.Path(arm).stem}_wall_{next(_SCENE_COUNT)}.xml"
    path.write_text(spec.to_xml())
    return str(path)


_SCENE_COUNT = itertools.count()


@functools.cache
def _scene_dir() -> tempfile.TemporaryDirectory:
    """The process's folder of generated scenes, removed when the interpreter exits (each process used to
    leave a ``jaxlimits_wall_*`` folder behind in the system's temporary directory)."""
    return tempfile.TemporaryDirectory(prefix="jaxlimits_wall_")


def check_wall_task(owner: str, n: int, home, normal, gap_low, gap_high) -> tuple:
    """``(home (n,), unit normal (3,), (gap_low, gap_high))`` of a wall-strike task, checked: ``ValueError`` naming
    ``owner`` and the field otherwise (``WallStrike``, ``strike.Strike``)."""
    home_arr = np.asarray(home, np.float64)
    if home_arr.shape != (n,) or not np.all(np.isfinite(home_arr)):
        raise ValueError(f"{owner}: home must be {n} finite joint positions, got {home!r}")
    nrm = np.asarray(normal, np.float64)
    if nrm.shape != (3,) or not np.all(np.isfinite(nrm)) or np.linalg.norm(nrm) < 1e-9:
        raise ValueError(f"{owner}: normal must be a non-zero 3-vector, got {normal!r}")
    if not 0.0 < gap_low <= gap_high:
        raise ValueError(f"{owner}: need 0 < gap_low <= gap_high, got {gap_low}, {gap_high}")
    return home_arr, nrm / np.linalg.norm(nrm), (float(gap_low), float(gap_high))


def _quat_z_to(direction) -> np.ndarray:
    """A unit quaternion (w, x, y, z) rotating the z axis onto ``direction`` (a plane's normal is its z)."""
    z = np.array([0.0, 0.0, 1.0])
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    c = float(z @ d)
    if c < -1 + 1e-12:
        return np.array([0.0, 1.0, 0.0, 0.0])
    axis = np.cross(z, d)
    q = np.concatenate([[1.0 + c], axis])
    return q / np.linalg.norm(q)


class WallStrike(ArmReach):
    """Strike and press a wall ahead of the end effector (MJX, contacts on).

    Args:
      normal: strike direction (3,), unit after normalisation (the wall's normal points back at the robot).
      arm, home: the arm's MJCF in ``assets/`` (``load_arm``'s conventions, a site ``ee``) and its start
        posture (n,) [rad].
      gap_low, gap_high: the wall is ``gap`` ahead of the ball's surface at reset, uniform [m].
      q_noise: initial joints are ``HOME`` + uniform(-q_noise, q_noise) [rad].
      c_range, dt_impact, tau_imp_scale, window: the impact model (``ImpactSpec``); the impulsive
        torque bound is ``tau_imp_scale * tau_max`` (motor torque limits by default).
      impulse_limit: reward clip on the normal impulse per step [N s]; contact_bonus per step in contact.
      ball_radius, solref, friction: contact parameters (``solref[0] = 0.004`` = 2 substeps is the
        stiffest MuJoCo allows at h = 2 ms).
      contact_model: the impact predictions' contact model (``jaxlimits.impact.ContactModel``); ``None``:
        ``CoulombContact(friction)``, the simulated contact (frictionless at ``friction = 0``). The
        paper's ``PaperContact()`` under-predicts a frictionless contact's jump of a light distal joint
        (see ``docs/impact.md``).
      **kwargs: ``ArmReach``'s (``torque_samples``, ``torque_margin``, ``seed``).
    """

    def __init__(
        self,
        normal=(1.0, 0.0, 0.0),
        gap_low: float = 0.005,
        gap_high: float = 0.05,
        q_noise: float = 0.1,
        c_range=(0.0, 0.2),
        dt_impact: float = 0.005,
        tau_imp_scale: float = 1.0,
        window: float = 0.02,
        impulse_limit: float = 2.0,
        contact_bonus: float = 1.0,
        ball_radius: float = 0.02,
        stop_fraction: float = 0.1,
        solref=(0.004, 1.0),
        friction: float = 1.0,
        arm: str = "panda.xml",
        home=HOME,
        contact_model=None,
        **kwargs,
    ):
        xml = wall_xml(float(ball_radius), tuple(float(x) for x in solref), float(friction), str(arm))
        super().__init__(xml, "ee", (0.2, -0.5, 0.1), (0.9, 0.5, 0.9), target="box", **kwargs)
        self.home, self.normal, self.gap = check_wall_task("WallStrike", self.n, home, normal, gap_low, gap_high)
        self.q_noise = float(q_noise)
        _impact.check_restitution(*c_range)  # validates eagerly
        if not dt_impact > 0 or not window > 0 or not tau_imp_scale > 0:
            raise ValueError(
                f"WallStrike: dt_impact, window, tau_imp_scale must be > 0, got {dt_impact}, {window}, {tau_imp_scale}"
            )
        contact = _impact.CoulombContact(friction) if contact_model is None else contact_model
        if not isinstance(contact, _impact.ContactModel):
            raise ValueError(f"WallStrike: contact_model must be a jaxlimits.impact.ContactModel, got {contact!r}")
        self.impact = ImpactSpec(
            tuple(float(c) for c in c_range), float(dt_impact), tau_imp_scale * self.tau_max, float(window), contact
        )
        self.h = float(self.mj_model.opt.timestep)
        self.window_substeps = max(1, int(round(window / self.h)))
        self.stop_fraction = float(stop_fraction)
        self.impulse_limit = float(impulse_limit)
        self.contact_bonus = float(contact_bonus)
        self.ball_radius = float(ball_radius)
        sim = mujoco.MjModel.from_xml_path(xml)
        sim.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_LIMIT | mujoco.mjtDisableBit.mjDSBL_EULERDAMP
        # this process's first device (mjx's default, jax.devices()[0], belongs to process 0 under jax.distributed)
        self.sys = mjx.put_model(sim, device=jax.local_devices()[0])
        self.ball = mujoco.mj_name2id(sim, mujoco.mjtObj.mjOBJ_GEOM, "ee_ball")
        self.wall_quat = _quat_z_to(-self.normal)

    @property
    def observation_size(self) -> int:
        return 3 * self.n + 6 + 1

    # ---- reset --------------------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> State:
        k_q, k_g = jax.random.split(rng)
        q = jnp.asarray(self.home, jnp.float32) + jax.random.uniform(
            k_q, (self.n,), jnp.float32, -self.q_noise, self.q_noise
        )
        gap = jax.random.uniform(k_g, (), jnp.float32, *self.gap)
        return self.reset_to_wall(q, jnp.zeros_like(q), gap)

    @_mjx_tracing
    def reset_to_wall(self, q, v, gap) -> State:
        """A state at ``(q, v)`` with the wall ``gap`` [m] ahead of the ball's surface along ``normal``."""
        nrm = jnp.asarray(self.normal, jnp.float32)
        ball = self.ee_position(q)
        wall = ball + (self.ball_radius + jnp.asarray(gap, jnp.float32)) * nrm
        d = mjx.make_data(self.sys)
        d = d.replace(
            qpos=self._f32(q),
            qvel=self._f32(v),
            mocap_pos=wall[None],
            mocap_quat=jnp.asarray(self.wall_quat, jnp.float32)[None],
        )
        d = mjx_stages.fwd_position(self.sys, d)
        zero = jnp.zeros((), jnp.float32)
        metrics = {f"violation/{k}": zero for k in VIOLATION_KEYS}
        metrics.update({f"count/{k}": zero for k in VIOLATION_KEYS})
        metrics.update(
            {
                "distance": zero,
                "accel_error": zero,
                "model_error": zero,
                "contact": zero,
                "disturbance": zero,
                "impact/hit": zero,
                "impact/w": zero,
                "impact/tau": zero,
                "impact/tau_contact": zero,
                "impact/v_post": zero,
                "impulse": zero,
                "strike": zero,
                "success": zero,
                "strike_ratio": zero,
                "strike_cap_unmet": zero,
            }
        )
        n = self.n
        zn = jnp.zeros((n,), jnp.float32)
        info = {
            "target": wall,
            "a_prev": zn,
            "gap": jnp.asarray(gap, jnp.float32),
            "impact": self._fresh_impact(d),
        }
        return State(d, self._obs(d, wall), zero, zero, metrics, info)

    def _fresh_impact(self, d) -> dict:
        """An armed impact record (``strike_record.fresh``, no strike measured yet) at ``d`` (positions computed), with
        this env's own fields: the joint momentum change and largest joint speeds over the window, the ball's centre
        and last normal velocity."""
        zero = jnp.zeros((), jnp.float32)
        zn = jnp.zeros((self.n,), jnp.float32)
        return {
            **strike_record.fresh(self.n),
            "momentum": zn,
            "vmax": zn,
            "ball_prev": self._ball_center(d),
            "w_last": zero,
        }

    def _ball_center(self, d):
        return d.geom_xpos[self.ball]

    def _obs(self, d, target):
        ee = d.site_xpos[self.ee_site]
        dist = jnp.sum((target - ee) * jnp.asarray(self.normal, jnp.float32))[None] - self.ball_radius
        return jnp.concatenate([jnp.cos(d.qpos), jnp.sin(d.qpos), d.qvel, ee, target - ee, dist]).astype(jnp.float32)

    # ---- model quantities for the shield ------------------------------------------------------
    def impact_terms(self, q, v):
        """``(M, J, normal)`` at ``(q, v)`` for ``jaxlimits.impact`` (single state)."""
        M, _ = self.mass_and_bias(q, v)
        return M, self.ee_jacobian(q), jnp.asarray(self.normal, jnp.float32)

    # ---- physics with contacts ----------------------------------------------------------------
    def _substep_contact(self, carry, a, band=None, cap_unmet=False, capped=False):
        d, imp = carry
        M, h, d = self.inverse_dynamics(d)  # fwd_position (collisions at this state) + fwd_velocity
        tau = M @ a + h
        in_contact = jnp.any(d._impl.contact.dist < 0.0)
        d_free = d
        d = _solve(self.sys, self._actuate(d_free, tau))
        tau_max = self._f32(self.tau_max)
        # the motors cannot apply the torque realising a (clipped at ctrlrange): a saturation unless a contact
        # correction took over (then its miss says it, as MjxActuation reports it)
        saturated = jnp.any(jnp.abs(tau) > tau_max)
        demanded = tau  # the torque the step's metrics compare with the motors' range (``_limit_metrics``)
        if band is not None:
            # the contact correction (envs/actuation.py): where the wall pushes the realised acceleration out of
            # the shield's band, the motors get the torque that brings it back under the contact's response
            # (saturation = a torque violation, counted). Not in a strike (its first substep or its open
            # window): the velocity jump is the impact cap's to bound, and pushing back would add to it.
            impl = d._impl
            D_active = jnp.where(impl.efc_force != 0, impl.efc_D, 0.0)
            qfrc = d.qfrc_smooth + d.qfrc_constraint
            applied = jnp.clip(tau, -tau_max, tau_max)  # what the motors applied in the solve (ctrlrange)
            dtau, out, dqacc, fix_miss = contact_correction(
                jnp, np.arange(self.n), M, M, impl.efc_J, D_active, qfrc, band, (-tau_max - applied, tau_max - applied)
            )
            in_strike = strike_record.in_strike(imp, in_contact)
            corrected = ~in_strike & jnp.any(out != 0)
            tau = jnp.where(in_strike, tau, applied + dtau)
            saturated = jnp.where(corrected, jnp.any(fix_miss != 0), saturated)
            # corrected: the boxed torque plus what it still lacked (the miss at the joints' inertia, as
            # actuation._boxed_inversion estimates it); elsewhere the command itself, whose clip the band may contain
            demanded = jnp.where(corrected, tau - M @ fix_miss, demanded)
            d = _solve(self.sys, self._actuate(d_free.replace(qacc_warmstart=d.qacc + dqacc), tau))
        frc = d.qfrc_constraint
        d_act = d.qfrc_actuator
        v_before, q_before = d.qvel, d.qpos
        d = mjx_stages.implicit(self.sys, d) if self._implicit else mjx_stages.euler(self.sys, d)
        ball = self._ball_center(mjx_stages.kinematics(self.sys, d))
        nrm = jnp.asarray(self.normal, jnp.float32)
        # impact bookkeeping (strike_record): the ball's normal velocity is the finite difference of its centre over
        # the substep, so the approach speed before it is the last substep's
        w_now = jnp.sum((ball - imp["ball_prev"]) * nrm) / self.h
        new, in_window = strike_record.advance(
            imp,
            in_contact,
            imp["w_last"],
            w_now,
            q_before,
            v_before,
            frc,
            self.h,
            self.window_substeps,
            self.stop_fraction,
            cap_unmet=cap_unmet,
            # the motors could not realise the substep's acceleration: a cap decided but not realised (only where
            # the shield has a cap)
            saturated=saturated & capped,
        )
        new.update(
            momentum=imp["momentum"] + jnp.where(in_window, (frc + d_act - h) * self.h, 0.0),
            vmax=jnp.where(in_window | (new["hit"] > 0), jnp.maximum(imp["vmax"], jnp.abs(d.qvel)), imp["vmax"]),
            ball_prev=ball,
            w_last=w_now,
        )
        return (d, new), (d.qpos, d.qvel, d.qacc, demanded, in_contact.astype(jnp.float32), frc * self.h)

    def _actuate(self, d, tau):
        """The motors' ctrl ``tau`` [N m] (gear 1), then actuation and smooth acceleration (before the solve)."""
        return mjx_stages.fwd_acceleration(self.sys, mjx_stages.fwd_actuation(self.sys, d.replace(ctrl=tau)))

    @_mjx_tracing
    def step_acc(self, state: State, a: jax.Array, band=None, cap_unmet=False, capped=False) -> State:
        """One control step of ``frame_skip`` substeps with joint acceleration ``a`` held; contacts on.

        ``band = (lower, upper)`` ``(n,)`` each [rad/s^2] (the shield's bounds): the contact correction keeps
        every substep's realised acceleration inside it where the motors can (see ``_substep_contact``).
        ``cap_unmet``: ``()`` bool, the shield's impact cap could not be met in this step (``strike_record``: a
        strike that begins in it or the next is outside the cap's claim, metric ``strike_cap_unmet``); ``capped``:
        ``()`` bool, the shield has an impact cap (then a substep whose motors saturated flags the strikes its
        approach sets too: the cap decided but not realised)."""
        a = self._f32(a)
        d0 = state.pipeline_state
        # an episode's first step (d0.time == 0: reset() or Brax's AutoResetWrapper, which restores the reset's
        # pipeline_state but not info) starts a fresh record, so that every episode's strike is measured
        kept = state.info["impact"]
        # and every strike is measured: once a strike's window has closed and the ball was off the wall for a whole
        # step (no substep in contact), the record re-arms, so the next contact (a re-strike after a bounce or a
        # pull-back) is measured too
        first_step = d0.time == 0
        imp0 = strike_record.start_step(kept, self._fresh_impact(d0), first_step)
        (d, imp), (qs, vs, accs, taus, contact, frcs) = jax.lax.scan(
            lambda c, _: self._substep_contact(c, a, band, cap_unmet, capped), (d0, imp0), None, length=self.frame_skip
        )
        step_imp = jnp.sum(frcs, axis=0)
        d = mjx_stages.fwd_position(self.sys, d)
        lim = self.limits
        f = self._f32
        zero = jnp.zeros((), jnp.float32)
        metrics = self._limit_metrics(state, d, a, qs, vs, accs, taus)
        target = state.info["target"]
        nrm = f(self.normal)
        ee = d.site_xpos[self.ee_site]
        dist = jnp.maximum(jnp.sum((target - ee) * nrm) - self.ball_radius, 0.0)
        metrics["distance"] = dist
        in_contact = jnp.max(contact)
        metrics["contact"] = in_contact
        metrics["disturbance"] = in_contact  # the evaluator's name: a contact acted on the arm in this step
        spec = self.impact
        imp, strike = strike_record.finish(imp0, imp, in_contact, spec.dt_impact, spec.tau_imp_max, cap_unmet=cap_unmet)
        metrics["impact/hit"] = imp["hit"]
        metrics["impact/w"] = imp["w"]
        metrics["impact/tau"] = strike_record.impulsive_ratio(imp["momentum"], spec.dt_impact, spec.tau_imp_max)
        metrics["impact/tau_contact"] = strike_record.impulsive_ratio(imp["impulse"], spec.dt_impact, spec.tau_imp_max)
        metrics["impact/v_post"] = jnp.max(imp["vmax"] / f(lim.v_max))
        # a strike is counted once, in the step its window closes: a violation when the impulsive joint torque
        # of its contact impulse (J^T p / dt_impact, the paper's J^T F; the motors' own torque over the window
        # left out) exceeds the bound (excess as a fraction of the bound)
        metrics["violation/impact"] = strike["excess"]
        metrics["count/impact"] = (strike["excess"] > 0).astype(jnp.float32)
        metrics["strike"] = strike["strike"]
        metrics["strike_ratio"] = strike["ratio"]  # measured / bound, once a strike
        metrics["strike_cap_unmet"] = strike["cap_unmet"]  # its approach under an unmet cap: outside its claim
        metrics["success"] = imp["struck"]  # the task: strike the wall (the evaluator's success)
        # normal impulse delivered this step [N s]: the wall's impulse on the ball from the joint impulse,
        # J^T p = sum(qfrc_constraint) h, solved in the least-squares sense (regularised)
        Jee = self.ee_jacobian_at(d0)  # d0: a state's pipeline_state, its position stage computed
        p = jnp.linalg.solve(Jee @ Jee.T + 1e-6 * jnp.eye(3, dtype=Jee.dtype), Jee @ step_imp)
        normal_impulse = jnp.maximum(jnp.sum(p * -nrm), 0.0)
        metrics["impulse"] = normal_impulse
        reward = -dist + self.contact_bonus * in_contact + jnp.minimum(normal_impulse, self.impulse_limit)
        info = dict(state.info)
        info["a_prev"] = a
        info["impact"] = imp
        return state.replace(
            pipeline_state=d, obs=self._obs(d, target), reward=reward, done=zero, metrics=metrics, info=info
        )


def _solve(m, d):
    return mjx_stages.solve(m, d)


def make_wall_strike(**kwargs) -> WallStrike:
    """The Panda wall-strike env (see ``WallStrike``)."""
    return WallStrike(**kwargs)


PLANAR_WALL = dict(
    arm="planar3.xml",
    home=PLANAR_HOME,
    normal=(1.0, 0.0, 0.0),
    gap_low=0.05,
    gap_high=0.25,
    c_range=(0.0, 0.4),
    friction=0.0,
)


def make_planar_wall_strike(**kwargs) -> WallStrike:
    """The planar 3-link arm strikes a wall 5-25 cm ahead along +x (``PLANAR_WALL``, overridable; see
    ``WallStrike``): the contact task fast enough to train on a CPU."""
    return WallStrike(**{**PLANAR_WALL, **kwargs})


# ---- a scripted striker (for measurements and tests) -------------------------------------------
def strike_command(env: WallStrike, state: State, speed, gain: float = 20.0):
    """Joint acceleration [rad/s^2] that drives the end effector along ``normal`` at ``speed`` [m/s].

    Resolved-rate with a damped pseudo-inverse: ``a = J^+ gain (speed n̂ - J v) - gain N v`` (the
    null-space motion is damped). Single state.
    """
    d = state.pipeline_state
    J = env.ee_jacobian_at(d)
    v = d.qvel
    nrm = jnp.asarray(env.normal, jnp.float32)
    err = speed * nrm - J @ v
    JJt = J @ J.T + 1e-4 * jnp.eye(3, dtype=J.dtype)
    pinv = J.T @ jnp.linalg.solve(JJt, jnp.eye(3, dtype=J.dtype))
    null = jnp.eye(env.n, dtype=J.dtype) - pinv @ J
    return gain * (pinv @ err) - gain * (null @ v)


def strike_experiment(env: WallStrike, shields, batch: int, steps: int = 40, speed_range=(0.05, 1.5), seed: int = 0):
    """Randomised strikes: each env draws a wall gap and a commanded speed, the scripted striker
    (``strike_command``, scaled uniformly into ``[-a_max, a_max]``: the direction is kept) drives the end effector into the wall through its shield.

    ``shields``: ``SafetyWrapper`` instances around ``env``; ``batch`` strikes per shield; one jit
    (every shield is computed, each env keeps its own). Returns a dict name -> dict of per-strike
    numpy arrays: ``speed`` (commanded), ``gap``, ``hit``, ``w`` (measured normal velocity at impact),
    ``tau`` and ``v_post`` (measured over their bounds, see ``WallStrike``), ``cap`` (the shield's cap in
    the last step before the impact; ``inf`` without ``impact=``), ``infeasible`` (steps flagged),
    ``violation_position``/``violation_velocity``/``violation_torque`` (max over the episode),
    ``violation_torque_free`` (max over the steps before its first contact), ``touched`` (1.0 once in contact),
    ``q_pre``, ``v_pre``, ``impulse`` (joint impulse over the window [N m s]).
    """
    names = [w.name for w in shields]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate shield names {names}")
    S = len(shields)
    B = S * int(batch)
    sid_np = np.repeat(np.arange(S), int(batch))
    cache_key = (env, tuple(shields), int(batch), int(steps), tuple(float(x) for x in speed_range))
    run = _RUNS.get(cache_key)
    if run is None:
        run = _RUNS[cache_key] = jax.jit(_make_run(env, shields, batch, steps, speed_range, S, B, sid_np))
    out = jax.device_get(run(jax.random.PRNGKey(seed)))
    return {name: {k: np.asarray(v)[sid_np == i] for k, v in out.items()} for i, name in enumerate(names)}


_RUNS = {}  # compiled strike experiments, per (env, shields, batch, steps, speed_range): one compilation per shape


def _make_run(env, shields, batch, steps, speed_range, S, B, sid_np):
    def run(key):
        k_r, k_s = jax.random.split(key)
        states = jax.vmap(env.reset)(jax.random.split(k_r, int(batch)))
        states = jax.tree.map(lambda x: jnp.concatenate([x] * S, axis=0), states)  # same walls for every shield
        speeds = jax.random.uniform(k_s, (int(batch),), jnp.float32, *speed_range)
        speeds = jnp.concatenate([speeds] * S)
        sid = jnp.asarray(sid_np)
        a_max = jnp.asarray(env.limits.a_max, jnp.float32)
        capped = jnp.asarray([bool(w.impact) for w in shields])  # per shield: it has an impact cap

        def one(state, s_id, speed):
            a_des = strike_command(env, state, speed)
            a_des = a_des * jnp.minimum(1.0, jnp.min(a_max / jnp.maximum(jnp.abs(a_des), 1e-6)))  # scaled, not clipped
            cands = [w._shield(state, a_des) for w in shields]
            a_safe = jnp.stack([c[0] for c in cands])[s_id]
            caps = jnp.stack([c[2].get("impact_cap", jnp.float32(jnp.inf)) for c in cands])[s_id]
            infe = jnp.stack([c[2].get("impact_infeasible", jnp.float32(0.0)) for c in cands])[s_id]
            bands = [w.band(c[1], c[0]) for w, c in zip(shields, cands)]  # as SafetyWrapper.finish
            band = None
            if all(b is not None for b in bands):
                band = tuple(jnp.stack([b[i] for b in bands])[s_id] for i in range(2))
            ns = env.step_acc(state, a_safe, band, infe > 0, capped[s_id])
            return ns, caps, infe

        def body(carry, _):
            states, acc = carry
            ns, cap, infe = jax.vmap(one)(states, sid, speeds)
            m, imp = ns.metrics, ns.info["impact"]
            was_hit = acc["hit"] > 0
            # the first strike of each env, taken when its window closes (the record re-arms after it)
            take = (m["strike"] > 0) & ~was_hit
            first = _strike_figures(m, imp)
            acc = {
                **{k: jnp.where(take.reshape(take.shape + (1,) * (v.ndim - 1)), v, acc[k]) for k, v in first.items()},
                "cap": jnp.where(was_hit | (states.info["impact"]["hit"] > 0), acc["cap"], cap),
                "infeasible": acc["infeasible"] + infe,
                "violation_position": jnp.maximum(acc["violation_position"], m["violation/position"]),
                "violation_velocity": jnp.maximum(acc["violation_velocity"], m["violation/velocity"]),
                "violation_torque": jnp.maximum(acc["violation_torque"], m["violation/torque"]),
                # before the episode's first contact (the record's ``struck``, this step's contact included): the
                # torque limit's claim (a contact the motors cannot hold asks them for more, counted in
                # violation_torque)
                "violation_torque_free": jnp.maximum(
                    acc["violation_torque_free"], jnp.where(imp["struck"] > 0, 0.0, m["violation/torque"])
                ),
            }
            return (ns, acc), None

        z = jnp.zeros((B,), jnp.float32)
        zn = jnp.zeros((B, env.n), jnp.float32)
        acc0 = {"cap": z, "infeasible": z, "violation_position": z, "violation_velocity": z, "violation_torque": z}
        acc0["violation_torque_free"] = z
        acc0.update({k: z for k in ("hit", "w", "tau", "tau_contact", "v_post", "window")})
        acc0.update({k: zn for k in ("q_pre", "v_pre", "impulse", "momentum")})
        (final, acc), _ = jax.lax.scan(body, (states, acc0), None, length=steps)
        # a strike whose window is still open at the end is taken as it stands
        m, imp = final.metrics, final.info["impact"]
        open_hit = (acc["hit"] == 0) & (imp["hit"] > 0)
        last = _strike_figures(m, imp)
        for k, v in last.items():
            acc[k] = jnp.where(open_hit.reshape(open_hit.shape + (1,) * (v.ndim - 1)), v, acc[k])
        return dict(acc, speed=speeds, gap=final.info["gap"], touched=imp["struck"])

    return run


def _strike_figures(m, imp) -> dict:
    """The figures ``strike_experiment`` reports of a strike, from a step's metrics and impact record."""
    return {
        "hit": m["impact/hit"],
        "w": m["impact/w"],
        "tau": m["impact/tau"],
        "tau_contact": m["impact/tau_contact"],
        "v_post": m["impact/v_post"],
        "q_pre": imp["q_pre"],
        "v_pre": imp["v_pre"],
        "impulse": imp["impulse"],
        "momentum": imp["momentum"],
        "window": imp["k"],
    }


def rigid_prediction(env: WallStrike, q_pre, v_pre, c: float):
    """The rigid model's joint impulse ``M dq`` [N m s] (22) at the measured pre-impact states, (B, n)."""

    @jax.jit
    def pred(q, v):
        M, J, nrm = jax.vmap(env.impact_terms)(q, v)
        jump = _impact.impact_jump(M, J, nrm, v, c, env.impact.dt_impact)
        return jump.dtau * env.impact.dt_impact, jump.w

    return jax.device_get(pred(jnp.asarray(q_pre, jnp.float32), jnp.asarray(v_pre, jnp.float32)))


__all__ = [
    "HOME",
    "PLANAR_HOME",
    "PLANAR_WALL",
    "ImpactSpec",
    "WallStrike",
    "check_wall_task",
    "make_planar_wall_strike",
    "make_wall_strike",
    "rigid_prediction",
    "strike_command",
    "strike_experiment",
    "wall_xml",
]
