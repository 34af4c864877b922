"""``JointLimitShield``: the joint-limit shield around any Brax ``PipelineEnv`` on the MJX backend.

    env = JointLimitShield(brax.envs.get_environment("pusher", backend="mjx"), v_max=2.0)

What it takes over: the env's physics call. The wrapped env's own ``step`` runs unchanged (its
action scaling, reward, observation, termination) up to ``self.pipeline_step(pipeline_state, ctrl)``;
the shield replaces that method on the innermost env (an instance attribute shadowing
``PipelineEnv.pipeline_step``) by ``_shielded_pipeline_step``, and the innermost env's ``step`` and ``reset``
by ``_shielded_step``/``_shielded_reset`` (the env's own, plus the shield's ``info``/``metrics``), so the
shield runs however the env is reached: Brax's ``DomainRandomizationVmapWrapper`` (the trainers'
``randomization_fn``) calls the innermost env's ``step``/``reset`` directly, past the wrappers in between
(a ``NonFiniteActionGuard`` acts at the innermost env too; other wrappers in between do not run), and sets each
member's System on it: the substeps run that System, and the
actuators' gains, ranges, damping are read from it (``MjxActuation.with_system``; the robot's limits,
``a_max`` included, stay those of the System given at construction, so a randomised robot too weak for them
saturates, counted). ``_shielded_pipeline_step``:

1. runs the first substep's position/velocity/actuation stages with the env's ``ctrl`` and reads the
   joint acceleration that ``ctrl`` asks for (``MjxActuation.asked_acceleration``: for a servo, its
   acceleration at the step's start state);
2. decides the safe acceleration (``SafeAcceleration``: the bounds of ``jl.acc_bounds`` for the
   model's integrator and ``n_frames`` substeps, the projection, braking for a NaN/inf command);
3. realises it at every substep through the model's actuators (``MjxActuation.finish_substep``: the
   shielded actuators' ctrl is recomputed per substep from the substep's state, the others keep the
   env's), with the contact correction where the model has contacts, then the model's own
   integrator; records the excess over the position/velocity limits and the torque the actuators lacked
   (saturation) at every substep.

All three run in one ``lax.scan`` over the substeps, the decision under a ``lax.cond`` on the substep
index (unbatched under ``vmap``, so a real branch, taken in the first substep only): every stage is
compiled once (the shielded pusher step compiles in 76 s here instead of 87 s; the same cost per step).

The outputs of that call reach ``step`` through the trace (``_pending``/``_outputs``, set and read in
the same call of ``step``): ``env.step`` must call ``pipeline_step`` once, outside any
``lax.cond``/``scan`` of its own (every Brax env does; anything else raises). A ``NonFiniteActionGuard``
outside the shield (``envs/nonfinite_guard.py``) keeps a NaN action out of the env's reward and observation
too; the shield brakes on the step it flags.

Per step: ``state.info["violation"] = {"position", "velocity", "torque"}`` (largest excess over the
step's substeps [rad or m, rad/s or m/s, N m or N]), with ``"jerk"`` too where the robot has ``j_max``
(``max |a_safe - a_prev| - j_max dt`` [rad/s^2]: the change of the held acceleration from the last step's, as
``ArmReach`` measures it; ``a_prev`` is 0 after a reset) and ``"impact"`` where an ``ImpactPoint`` names what strikes
(a strike's measured impulsive joint torque over its bound, less 1, counted once in the step its window closes:
``envs/strike_record.py``), and ``state.metrics["shield/*"]``: the same,
``intervention`` (``max |a_safe - a_des|``), ``saturated``, ``nonfinite``, ``nonviable`` (0/1 per
step), ``accel_error`` (``max |(v+ - v)/h - a_safe|`` over substeps and joints: contact forces,
saturation and RK4's second-order error show here) and ``disturbance`` (largest constraint force [N m]
on a shielded dof while inside its limits: a contact), ``torque_conflict`` (0/1: not even the
position/velocity/viability bounds were realisable) and ``beyond_bounds`` (how far the realised
decision left the acceleration/jerk limit because no acceleration inside it was realisable, e.g. a
servo that cannot hold back gravity braking harder than ``a_max`` [rad/s^2]), ``contact_corrected``
(how far a contact would have pushed a substep's realised acceleration out of the bounds before the
correction [rad/s^2]). The guarantee is exact for the model's own dynamics. A contact's force depends on
the acceleration: where one would push the realised acceleration out of the bounds, the actuators are
given the least torque change, within what they have left, that holds it inside the bounds under the
contact's own response (``MjxActuation.finish_substep``, ``correct_contacts=True``); where they lack that
torque (a hard impact, e.g. Brax ``pusher``'s hand striking its table), the contact pushes the joint on: a
saturation and, maybe, a violation, both counted. A trajectory no contact touched never violates (measured).
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from brax.base import Contact, Motion, Transform
    from brax.envs.base import PipelineEnv, State, Wrapper
    from brax.mjx import pipeline as brax_mjx_pipeline

from jaxlimits.envs import mjx_stages, nonfinite_guard, strike_record
from jaxlimits.internal import batched_like
from jaxlimits.envs.actuation import MjxActuation
from jaxlimits.envs.impact_point import ImpactPoint
from jaxlimits.envs.arm import _mjx_tracing
from jaxlimits.envs.joint_shield import BOUNDS_TOL, Decision, SafeAcceleration
from jaxlimits.envs.robot import Robot, sub_block

VIOLATIONS = ("position", "velocity", "torque")
SHIELD_METRICS = VIOLATIONS + (
    "intervention",
    "saturated",
    "nonfinite",
    "nonviable",
    "accel_error",
    "disturbance",
    "torque_conflict",
    "beyond_bounds",
    "contact_corrected",
)
# with an impact cap (``impact=``): the cap [m/s], 0/1 where no command inside the bounds and the torques met it,
# the impact point's largest approach speed along the normal over the step's substeps [m/s], and 0/1 whether the cap
# applied (``ImpactPoint.surface``: only near it); and the point's strikes, measured (``envs/strike_record.py``): 1.0 in
# the step a strike's window closes, and its impulsive joint torque over ``tau_imp_max`` and approach speed [m/s] then,
# and 1.0 then if the cap was unmet in the step the strike began in or the one before (outside the cap's claim)
IMPACT_METRICS = (
    "impact_cap",
    "impact_infeasible",
    "impact_speed",
    "impact_active",
    "strike",
    "strike_ratio",
    "strike_speed",
    "strike_cap_unmet",
)
# fields a Brax env may have changed on its System after loading (read back into the MjModel copy)
_SYNCED_FIELDS = (
    "actuator_gear",
    "actuator_gainprm",
    "actuator_biasprm",
    "actuator_ctrlrange",
    "actuator_forcerange",
    "jnt_actfrcrange",
    "jnt_range",
    "dof_damping",
    "dof_armature",
)
# fields a user (e.g. a domain randomisation) may have changed on the System: the robot's braking capacity (masses),
# its spring model, the rows the correction covers (friction loss) and its actuator types read them; read back only
# where they differ beyond the System's float32 copy
_SYNCED_IF_CHANGED = (
    "body_mass",
    "body_inertia",
    "body_ipos",
    "dof_frictionloss",
    "jnt_stiffness",
    "qpos_spring",
    "actuator_biastype",  # which actuators the robot supports and inverts (a motor made a servo on the System)
    "actuator_gaintype",
    "actuator_dyntype",
)
# the options a Brax env may have changed on ``sys.opt`` (``ant`` and ``humanoid`` on MJX disable Euler's implicit
# damping and run one solver iteration): the robot's integrator model is read from them (``Robot.implicit_damping``)
_SYNCED_OPTIONS = (
    "integrator",
    "disableflags",
    "enableflags",
    "cone",
    "solver",
    "iterations",
    "ls_iterations",
    "tolerance",
    "ls_tolerance",
    "impratio",
    "gravity",
    "wind",
    "magnetic",
    "density",
    "viscosity",
)


def _mj_model_of(sys):
    """A copy of the ``MjModel`` a Brax ``System`` was built from, with the fields and options Brax envs edit on
    the System (e.g. ``pusher``'s gear for other backends, ``ant``'s ``opt.disableflags``) read back from it, and
    the masses, springs and friction loss where the System's differ (``_SYNCED_IF_CHANGED``)."""
    mjm = getattr(sys, "mj_model", None)
    if mjm is None:
        raise TypeError("the env's System has no mj_model (built without brax.io.mjcf?)")
    mjm = mjm.__copy__()
    for name in _SYNCED_FIELDS:
        getattr(mjm, name)[:] = np.asarray(getattr(sys, name))
    mjm.opt.timestep = float(sys.opt.timestep)  # the step MJX takes (float32)
    changed = [(mjm, name, getattr(sys, name)) for name in _SYNCED_IF_CHANGED]
    changed += [(mjm.opt, name, getattr(sys.opt, name)) for name in _SYNCED_OPTIONS]
    for owner, name, value in changed:
        value = np.asarray(value)
        if np.array_equal(np.asarray(getattr(owner, name)).astype(value.dtype), value):
            continue  # unchanged (kept in float64: the System holds float32 copies)
        if value.ndim:
            getattr(owner, name)[:] = value
        else:
            setattr(owner, name, value.item())
    return mjm


def _contact_joint_force(d, dofs) -> jax.Array:
    """``(n,)`` the contacts' joint force on the shielded dofs in MJX data ``d`` after its constraint solve [N m or N]:
    ``efc_J^T efc_force`` over the contact rows (every contact's: a strike's force reaches the joints through the
    whole arm; the joint-limit rows left out)."""
    impl = d._impl if hasattr(d, "_impl") else d
    if impl.efc_J.shape[0] == 0:
        return jnp.zeros((len(dofs),), d.qvel.dtype)
    contact = impl.efc_type >= int(mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS)
    return (jnp.where(contact, impl.efc_force, 0.0) @ impl.efc_J)[np.asarray(dofs)]


def _brax_state(sys, d):
    """The Brax fields of the MJX pipeline state (as ``brax.mjx.pipeline.step`` computes them)."""
    x = Transform(pos=d.xpos[1:], rot=d.xquat[1:])
    cvel = Motion(vel=d.cvel[1:, 3:], ang=d.cvel[1:, :3])
    offset = Transform.create(pos=d.xpos[1:, :] - d.subtree_com[sys.body_rootid[1:]])
    xd = offset.vmap().do(cvel)
    d = d.replace(q=d.qpos, qd=d.qvel, x=x, xd=xd)
    impl = d._impl if hasattr(d, "_impl") else d
    if impl.ncon > 0:
        c = impl.contact
        body1 = jnp.array(sys.geom_bodyid)[c.geom1] - 1
        body2 = jnp.array(sys.geom_bodyid)[c.geom2] - 1
        contact = Contact(link_idx=(body1, body2), elasticity=jnp.zeros(c.pos.shape[0]), **c.__dict__)
        d = d.replace(contact=contact)
    return d


class JointLimitShield(Wrapper):
    """Shield a Brax MJX ``PipelineEnv``'s joints; see the module docstring.

    Args:
      env: a Brax env (possibly wrapped) whose innermost env is a ``PipelineEnv`` with backend ``"mjx"``.
      joints: names of the shielded joints (default: every hinge/slide joint an actuator drives).
      v_max, a_max, j_max: limits, scalar or per joint (``Robot.from_model``: MJCF numerics, else
        ``a_max`` torque-derived; ``v_max`` is required unless the MJCF has it).
      method: ``"viability"``, ``"jerk"``, ``"naive"`` or ``"none"`` (``joint_shield.METHODS``).
      gradient: derivative of the projection (``jl.project_box``): ``"exact"`` or ``"straight_through"``.
      torque_limits: decide among the accelerations the actuators can realise at the step's start state
        (``SafeAcceleration`` with an ``actuation.TorqueModel``: a box QP in torque space; when none inside
        the bounds is realisable, counted in ``shield/torque_conflict``). Without it, a command the
        actuators cannot deliver saturates them and, through the coupling of ``M``, moves the other
        joints off their commands too.
      correct_contacts: where a contact would push a substep's realised acceleration out of the bounds, give
        the actuators the torque that holds it at their edge (``actuation`` module docstring; a second
        constraint solve per substep, warm-started: +~30 % of the pusher's step at batch 256); measured in
        ``shield/contact_corrected``.
      start_inside: move the env's initial pose (``sys.init_q``, which Brax's resets add their noise to) inside the
        shielded joints' ranges shrunk by its reset noise (``_reset_noise_scale``, 0 where the env has none) and 1 %
        (``Robot.pose_inside``): Brax's ``pusher`` starts its elbow and wrist flex at their upper limits, ``hopper``
        and ``walker2d`` their hips and knees, states outside any guarantee (counted as non-viable otherwise).
      impact: ``None`` or an ``ImpactPoint`` (``envs/impact_point.py``): the impact-aware speed cap on that point's
        approach speed along its normal, one more row of the decision; metrics ``shield/impact_cap``,
        ``shield/impact_infeasible``, ``shield/impact_speed``, ``shield/impact_active`` (``IMPACT_METRICS``). Its
        strikes are measured at every substep (``envs/strike_record.py``, the record in ``info["shield_strike"]``):
        ``info["violation"]["impact"]`` (a strike's measured impulsive joint torque over ``tau_imp_max``, less 1, in
        the step its window closes) and metrics ``shield/strike`` (1.0 then), ``shield/strike_ratio``,
        ``shield/strike_speed`` (its approach speed [m/s]), ``shield/strike_cap_unmet`` (1.0 then if the enforced cap
        was not delivered in the step the strike began in, before its contact, or the one before: unmet, or an
        actuator saturated; outside the cap's claim). In a strike (its first substep and its open window) an
        enforced cap turns the contact correction off: the velocity jump is the cap's to bound, and holding the
        acceleration in the bounds would push the point on into the surface (measured: a block dropped at the cap
        struck at 1.45 times its bound with the correction on, ``tests/test_strike_record.py``).
      robot_kwargs: passed to ``Robot.from_model`` (``torque_margin``, ``torque_samples``, ...).

    Attributes: ``robot`` (``Robot``), ``decide`` (``SafeAcceleration``), ``actuation``, ``impact``
    (``impact_point.ImpactModel`` or ``None``), ``violations`` (the kinds ``info["violation"]`` holds: ``VIOLATIONS``,
    ``"jerk"`` where the robot has ``j_max``, ``"impact"`` with an impact point).
    """

    def __init__(
        self,
        env,
        joints=None,
        v_max=None,
        a_max=None,
        j_max=None,
        method: str = "viability",
        gradient: str = "exact",
        torque_limits: bool = True,
        correct_contacts: bool = True,
        start_inside: bool = False,
        impact: ImpactPoint | None = None,
        **robot_kwargs,
    ):
        super().__init__(env)
        if impact is not None and not isinstance(impact, ImpactPoint):
            raise TypeError(f"impact must be None or an ImpactPoint, got {type(impact).__name__}")
        self.torque_limits = bool(torque_limits) and method != "none"
        self.correct_contacts = bool(correct_contacts) and method != "none"
        base = env.unwrapped
        if not isinstance(base, PipelineEnv) or getattr(base, "backend", None) != "mjx":
            raise TypeError(
                f"JointLimitShield wraps a Brax PipelineEnv on the mjx backend, got {type(base).__name__}"
                f" (backend {getattr(base, 'backend', None)!r})"
            )
        if "_shielded_by" in base.__dict__:
            raise ValueError("this env is already shielded (one JointLimitShield per env)")
        if type(base).pipeline_step is not PipelineEnv.pipeline_step:
            raise ValueError(
                f"{type(base).__name__} overrides PipelineEnv.pipeline_step, the physics call the shield takes over: "
                "its own code would not run under the shield. Move that code into the env's step (around "
                "pipeline_step), or shield an env that keeps Brax's pipeline_step"
            )
        self.n_frames = int(base._n_frames)
        robot_kwargs.setdefault("control_dt", float(base.sys.opt.timestep) * self.n_frames)
        self.robot = Robot.from_model(_mj_model_of(base.sys), joints, v_max, a_max, j_max, **robot_kwargs)
        if start_inside:  # before the actuation reads base.sys (MjxActuation.with_system: the System given)
            init_q = base.sys.init_q
            inside = self.robot.pose_inside(np.asarray(init_q), getattr(base, "_reset_noise_scale", 0.0))
            base.sys = base.sys.replace(init_q=jnp.asarray(inside, init_q.dtype))
        self.impact = None if impact is None else impact.resolve(_mj_model_of(base.sys), self.robot)
        # the kinds of info["violation"]: jerk where the robot has a jerk limit to measure it against, the strikes'
        # impulsive joint torque where an impact point names what strikes
        self.violations = VIOLATIONS + (("jerk",) if self.robot.limits.j_max is not None else ())
        self.violations += ("impact",) if self.impact is not None else ()
        self._metric_names = SHIELD_METRICS + self.violations[len(VIOLATIONS) :]
        self._metric_names += IMPACT_METRICS if self.impact is not None else ()
        # MJX computes in float32: the limits keep clear of the servos' ctrl rounding (joint_shield's docstring)
        self.decide = SafeAcceleration(
            self.robot, self.n_frames, method, gradient, realisation_margin=True, impact=self.impact
        )
        self.actuation = MjxActuation(self.robot, base.sys)
        self.method = method
        self._base = base
        self._pending = None
        self._outputs = None
        base._shielded_by = self
        base.pipeline_step = self._shielded_pipeline_step  # the physics call
        if type(base).pipeline_init is PipelineEnv.pipeline_init and base._pipeline is brax_mjx_pipeline:
            base.pipeline_init = self._staged_pipeline_init  # reset's physics, MJX traced once per model
        # and the env's own step and reset, so the shield runs however the env is reached: Brax's
        # DomainRandomizationVmapWrapper (``randomization_fn`` of its trainers) calls the innermost env's step and
        # reset (``env.unwrapped``) inside its vmap, past every wrapper in between, this one too
        self._env_step, self._env_reset = base.step, base.reset
        base.step, base.reset = self._shielded_step, self._shielded_reset

    @property
    def limits(self):
        """The shielded joints' ``jl.JointLimits`` (``robot.limits``), as the project's own envs name them."""
        return self.robot.limits

    # ---- the physics call --------------------------------------------------------------------
    def _staged_pipeline_init(self, q, qd, act=None, ctrl=None):
        """``PipelineEnv.pipeline_init`` (Brax's mjx ``init``) with ``mjx.forward`` traced once per model
        (``mjx_stages.brax_pipeline_init``); the System read at the call (a domain randomisation's)."""
        return mjx_stages.brax_pipeline_init(self._base.sys, q, qd, act, ctrl, self._base._debug)

    @_mjx_tracing
    def _shielded_pipeline_step(self, pipeline_state, ctrl):
        if self._pending is None:
            raise RuntimeError("pipeline_step of a shielded env was called outside the env's step")
        # replaced: a NonFiniteActionGuard outside zeroed a non-finite action; kept: the strike record (impact=)
        a_prev, replaced, kept = self._pending
        rob, act = self.robot, self.actuation.with_system(self._base.sys)  # a domain randomisation's System
        dofs, qadr = np.asarray(rob.dof_adr), np.asarray(rob.qpos_adr)
        finite = jnp.isfinite(ctrl)
        ctrl_clean = jnp.where(finite, ctrl, 0.0)
        nonfinite = ~jnp.all(finite) | replaced
        h = jnp.float32(rob.timestep)
        tol = jnp.asarray(BOUNDS_TOL * rob.limits.a_max, jnp.float32)

        def decide(d, M, f):
            a_des = jnp.where(nonfinite, jnp.nan, act.asked_acceleration(d, M))  # braking substituted, flagged
            torque = act.torque_model(d, M, f, self.decide.dt) if self.torque_limits else None
            terms = None
            if self.impact is not None:  # the rigid-body mass matrix (no implicit damping) of the shielded chain
                imp = self.impact
                terms = (
                    sub_block(act.mass(M), dofs, dofs),
                    imp.jacobian(act.sys, d, dofs),
                    imp.jacobian_rate(act.sys, d, dofs),
                    imp.point_position(d),
                )
            return self.decide(d.qpos[qadr], d.qvel[dofs], a_des, a_prev, torque, terms), a_des

        def cap_unmet(dec):  # this step's impact cap could not be met (a measured-only point has no cap)
            return SafeAcceleration.impact_unmet(dec) & self.impact.enforce

        def record(d_before, d_after, inv, out, a, strike, touch, dec):
            v0, v1 = d_before.qvel[dofs], d_after.qvel[dofs]
            viol = self.decide.violations(d_after.qpos[qadr], v1)
            inside = self.decide.violations(d_before.qpos[qadr], v0)["position"] <= 0
            extra = {}
            if self.impact is not None:  # the impact point's approach speed at the substep's start, its strike
                imp = self.impact
                J = imp.jacobian(act.sys, d_before, dofs)
                extra["impact_speed"] = w0 = imp.approach_speed(J, v0)
                extra["striking"] = touch
                strike, _ = strike_record.advance(
                    strike,
                    touch,
                    w0,
                    imp.approach_speed(J, v1),
                    d_before.qpos[qadr],
                    v0,
                    _contact_joint_force(d_after, dofs),
                    h,
                    imp.window_substeps,
                    imp.stop_fraction,
                    cap_unmet=cap_unmet(dec),
                    saturated=jnp.any(inv.saturated) & imp.enforce,  # the cap decided, not realised
                )
            return strike, {
                **extra,
                **viol,
                # constraint force on the shielded dofs while they are inside their limits (MuJoCo's limit
                # constraint is inactive there): a contact (or friction loss, equality) the shield does not model
                "disturbance": jnp.where(inside, jnp.max(jnp.abs(d_after.qfrc_constraint[dofs])), 0.0),
                "torque": jnp.max(inv.torque_excess),
                "saturated": jnp.any(inv.saturated),
                "accel_error": jnp.max(jnp.abs((v1 - v0) / h - a)),
                # how far a contact would have pushed the realised acceleration out of the bounds (solver
                # roundoff at the bounds, below BOUNDS_TOL a_max, is not counted)
                "contact_corrected": jnp.max(jnp.where(jnp.abs(out) > tol, jnp.abs(out), 0.0)),
            }

        # One scan over the substeps, the decision made in the first (a cond on the substep index, which vmap
        # leaves unbatched, so a real branch): each stage is compiled once, not once for the first substep and
        # again for the others (MJX's stages dominate the shielded step's compilation).
        def substep(carry, i):
            dd, dec, a_des, strike = carry
            ds, Ms, fs = act.smooth_stage(dd, ctrl_clean)
            dec, a_des = jax.lax.cond(i == 0, lambda: decide(ds, Ms, fs), lambda: (dec, a_des))
            a = dec.a_safe
            # every substep's realised acceleration is kept inside the decision's bounds (a contact corrected)
            band = None if not self.correct_contacts else (jnp.minimum(dec.lower, a), jnp.maximum(dec.upper, a))
            touch = None
            if self.impact is not None:
                touch = self.impact.striking(ds)
                if band is not None and self.impact.enforce:
                    # no correction in a strike: the jump is the cap's to bound (strike_record.in_strike)
                    in_strike = strike_record.in_strike(strike, touch)
                    band = tuple(jnp.where(in_strike, jnp.inf * side, b) for side, b in zip((-1.0, 1.0), band))
            dn, inv, out = act.finish_substep(ds, Ms, fs, a, band)
            strike, rec = record(ds, dn, inv, out, a, strike, touch, dec)
            return (dn, dec, a_des, strike), rec

        dtype = pipeline_state.qvel.dtype
        vec, flag = jnp.zeros((rob.n,), dtype), jnp.zeros((), bool)
        zero = jnp.zeros((), dtype)
        dec0 = Decision(vec, vec, vec, jnp.zeros((rob.n,), bool), flag, flag, zero, zero, flag)
        strike0 = None
        if kept is not None:  # the record a step starts from: afresh at an episode's first step (time 0: also after
            # Brax's AutoResetWrapper, which restores the reset's pipeline_state but not info), re-armed after a strike
            strike0 = strike_record.start_step(kept, strike_record.fresh(rob.n), pipeline_state.time == 0)
        # one batching round under vmap
        init = batched_like((pipeline_state, dec0, vec, strike0), pipeline_state.qpos)
        (d_end, dec, a_des, strike_end), recs = jax.lax.scan(substep, init, jnp.arange(self.n_frames))
        a = dec.a_safe
        rec = {k: jnp.max(v) for k, v in recs.items()}
        finite_des = jnp.isfinite(a_des)
        rec["intervention"] = jnp.max(jnp.where(finite_des, jnp.abs(a - jnp.where(finite_des, a_des, 0.0)), 0.0))
        rec["nonfinite"] = dec.nonfinite | nonfinite
        rec["nonviable"] = ~jnp.all(dec.viable)
        rec["torque_conflict"] = dec.conflict
        rec["beyond_bounds"] = SafeAcceleration.beyond_bounds(dec)
        if "jerk" in self.violations:
            rec["jerk"] = self.decide.jerk_excess(a, a_prev)
        strike = None
        if self.impact is not None:
            rec["impact_cap"] = dec.impact_cap
            rec["impact_active"] = dec.impact_active
            rec["impact_infeasible"] = SafeAcceleration.impact_unmet(dec)
            imp = self.impact
            strike, figures = strike_record.finish(
                strike0, strike_end, rec.pop("striking"), imp.dt_impact, imp.tau_imp_max, cap_unmet=cap_unmet(dec)
            )
            rec.update(strike=figures["strike"], strike_ratio=figures["ratio"], strike_speed=figures["speed"])
            rec["strike_cap_unmet"] = figures["cap_unmet"]
            rec["impact"] = figures["excess"]
        self._outputs = (rec, dec, a_des, strike)
        return _brax_state(self._base.sys, d_end)

    # ---- Brax Env interface -------------------------------------------------------------------
    def reset(self, rng: jax.Array) -> State:
        return self.env.reset(rng)  # reaches ``_shielded_reset`` (the innermost env's reset)

    def step(self, state: State, action: jax.Array) -> State:
        return self.env.step(state, action)  # reaches ``_shielded_step``

    @_mjx_tracing
    def _shielded_reset(self, rng: jax.Array) -> State:
        state = self._env_reset(rng)
        n = self.robot.n
        zero = jnp.zeros((), jnp.float32)
        info = dict(state.info)
        info["shield_a_prev"] = jnp.zeros((n,), jnp.float32)
        info["violation"] = {k: zero for k in self.violations}
        if self.impact is not None:
            info["shield_strike"] = strike_record.fresh(n)
        metrics = dict(state.metrics)
        metrics.update({f"shield/{k}": zero for k in self._metric_names})
        return state.replace(info=info, metrics=metrics)

    @_mjx_tracing
    def _shielded_step(self, state: State, action: jax.Array) -> State:
        replaced = jnp.asarray(state.info.get(nonfinite_guard.FLAG, False), bool)
        kept = state.info["shield_strike"] if self.impact is not None else None
        self._pending, self._outputs = (state.info["shield_a_prev"], replaced, kept), None
        try:
            nstate = self._env_step(state, action)
            if self._outputs is None:
                raise RuntimeError("the wrapped env's step did not call pipeline_step")
            rec, dec, _, strike = self._outputs
        finally:
            self._pending = self._outputs = None
        info = dict(nstate.info)
        info["shield_a_prev"] = dec.a_safe.astype(jnp.float32)
        if strike is not None:
            info["shield_strike"] = strike
        info["violation"] = {k: rec[k].astype(jnp.float32) for k in self.violations}
        metrics = dict(nstate.metrics)
        metrics.update({f"shield/{k}": jnp.asarray(rec[k], jnp.float32) for k in self._metric_names})
        return nstate.replace(info=info, metrics=metrics)
