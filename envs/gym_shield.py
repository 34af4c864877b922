"""``JointLimitShieldWrapper``: the joint-limit shield around any Gymnasium ``MujocoEnv`` (C MuJoCo).

    env = JointLimitShieldWrapper(gymnasium.make("Pusher-v5"), v_max=2.0)
    obs, info = env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    info["violation"]  # {"position", "velocity", "torque"}: largest excess over the step's substeps
    info["shield"]     # the decision: intervention, saturated, nonfinite, viable, accel_error, a_des, ...

What it takes over: the env's physics call, and nothing else. ``MujocoEnv.step`` of every Gymnasium
MuJoCo env calls ``self.do_simulation(ctrl, self.frame_skip)``, which writes ``ctrl`` into
``data.ctrl`` and runs ``mj_step(model, data, nstep=n_frames)`` then ``mj_rnePostConstraint``. The
wrapper sets the *instance* attribute ``env.unwrapped.do_simulation = self._do_simulation``
(shadowing the class's method); the env's own ``step`` (its action handling, observation, reward,
termination, rendering) runs unchanged around it. ``_do_simulation(ctrl, n_frames)``:

1. cleans ``ctrl`` (``(nu,)``): an entry that MuJoCo would reject (NaN, inf or ``|x| > 1e10``,
   MuJoCo's ``mju_isBad``; MuJoCo itself would then zero the *whole* ``ctrl`` with a warning) is set
   to 0 and flagged ``nonfinite``; when it belongs to a shielded actuator the command for the shielded
   joints is unknown, so ``a_des`` is set to NaN and ``SafeAcceleration`` substitutes braking;
2. substep 0: runs the position/velocity/actuation stages with the env's ``ctrl`` and reads the joint
   acceleration ``a_des`` ``(n,)`` [rad/s^2 or m/s^2] that ``ctrl`` asks of the shielded joints
   (``CActuation.smooth_stage``; for a servo, its acceleration at the step's start state);
3. decides the safe acceleration ``a_safe`` (``SafeAcceleration``: ``jl.acc_bounds`` for the
   model's integrator over ``n_frames`` substeps, then the projection; one jitted, ahead-of-time
   compiled XLA call per control step, float32, cached per ``n_frames``);
4. realises ``a_safe``, *held* over the whole control step, at every substep through the model's own
   actuators: the shielded actuators' ``ctrl`` is recomputed per substep from that substep's state
   (``CActuation.finish_substep``; the other actuators keep the env's ``ctrl``), then the rest of the
   substep incl. the model's own integrator runs; substeps 1..n-1 re-run ``smooth_stage`` with the
   same env ``ctrl`` first (the state changed);
5. records, at every substep's end, the excess over the model's own limits (``robot.limits``:
   ``jnt_range`` for limited joints, unlimited joints have no position excess; ``v_max``), the torque
   the actuators lacked (a clamp to ``ctrlrange``/``forcerange`` is a *saturation*) and the realised
   acceleration error ``max |(v+ - v)/h - a_safe|``; finally ``mj_rnePostConstraint`` as Gymnasium does.

After the call ``data.ctrl`` holds the last substep's ctrl of the shielded actuators (the env's for the
others). The env also gets the attribute ``_shielded_by`` (one wrapper per env); nothing is restored on
``close``.

Contact and joint-limit constraint forces depend on the acceleration, so step 4's formula leaves them
out; ``info["shield"]["constrained"]`` says whether a constraint force acted on a shielded dof in some
substep. Where one would push a substep's realised acceleration out of the bounds, the substep is
corrected (``correct_contacts=True``, ``CActuation.finish_substep``: the constraint problem solved once
with the shield's ctrl, then the actuators given the least torque change, within what they have left, that
holds the acceleration inside the bounds under the contact's own response; ``info["shield"]["contact_corrected"]``
how far it would have left them). Where the actuators lack that torque (Gymnasium's Pusher striking its table), the contact
pushes the joint on: a saturation and, maybe, a violation, both counted (``tests/test_gym_shield.py``
measures it). Euler and
implicitfast realise ``a_safe`` exactly (to float64 roundoff) without constraint forces and
saturation; RK4 holds ``ctrl`` over its four stages, so it realises the held acceleration only to
second order in ``h`` (``robot.py``; ``SafeAcceleration`` tightens the limits for it by ``RK4_MARGIN``).

Worker processes (vectorised envs): JAX cannot run in a process forked after JAX started, so the wrapper refuses to
be built there with an error naming the start methods that work (``fork_guard``): Gymnasium's ``AsyncVectorEnv``
needs ``context="forkserver"`` (or ``"spawn"``); Stable-Baselines3's ``SubprocVecEnv`` works as it is.

Cost: the decision is one XLA call per control step (float32 numpy in, one packed array out); the
substeps run NumPy and C MuJoCo from Python, several times the env's own ``mj_step``
(``benchmarks/bench_gym_shield.py``).

``method="none"`` is the unshielded baseline through the same code (the command as asked, only the
NaN guard): it counts the violations the shield prevents.
"""

from __future__ import annotations

import warnings

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

from jaxlimits.envs.actuation import CActuation, TorqueModel, as_slice
from jaxlimits.envs.content_cache import LruCache
from jaxlimits.envs.fork_guard import check_not_forked_from_jax
from jaxlimits.envs import strike_record
from jaxlimits.envs.impact_point import ImpactPoint
from jaxlimits.envs.joint_shield import BOUNDS_TOL, RK4_MARGIN, RK4_RESTEP, SafeAcceleration
from jaxlimits.envs.robot import Robot

VIOLATIONS = ("position", "velocity", "torque")
MJ_MAXVAL = mujoco.mjMAXVAL  # mju_isBad(x) is NaN or |x| > mjMAXVAL (1e10)
_REQUIRED = ("model", "data", "do_simulation", "frame_skip")


def _zero_tally(violations=VIOLATIONS) -> dict:
    """The counters of ``JointLimitShieldWrapper.tally``: ``<k>_violations`` and ``max_<k>_excess`` per kind of
    ``violations``, the rest fixed (``strikes``, ``max_strike_ratio``: an impact point's measured strikes)."""
    return {
        "steps": 0,
        **{f"{k}_violations": 0 for k in violations},
        **{f"max_{k}_excess": 0.0 for k in violations},
        "saturated": 0,
        "nonfinite": 0,
        "nonviable": 0,
        "constrained": 0,
        "disturbed": 0,
        "torque_conflict": 0,
        "beyond_bounds": 0,
        "contact_corrected": 0,
        "starts_outside": 0,
        "impact_infeasible": 0,
        "max_impact_speed": 0.0,
        "strikes": 0.0,
        "max_strike_ratio": 0.0,
        "max_accel_error": 0.0,
        "max_intervention": 0.0,
        "max_beyond_bounds": 0.0,
        "max_contact_corrected": 0.0,
    }


_SHARED_DECIDERS = LruCache(32)  # (robot fingerprint, method, torque limits, n_frames, impact) -> decider


def _compile_decider(robot: Robot, n_frames: int, method: str, torque_limits: bool, impact=None):
    """``(SafeAcceleration, compiled)``: the decision for ``robot`` over ``n_frames`` substeps, jitted and compiled
    ahead of time for float32 ``(n,)`` inputs (``JointLimitShieldWrapper._decider``); ``impact`` an
    ``impact_point.ImpactModel`` (then four more inputs, ``M`` ``(n, n)``, ``J`` and ``J_rate`` ``(3, n)``, the point
    ``(3,)``, and three more outputs, the cap, whether it was unmet and whether it applied)."""
    decide = SafeAcceleration(robot, n_frames, method, impact=impact)

    def packed(q, v, a_des, a_prev, M_ss, f_s, tau_lo, tau_hi, *impact_terms):
        torque = TorqueModel(M_ss, f_s, tau_lo, tau_hi) if torque_limits else None
        dec = decide(q, v, a_des, a_prev, torque, impact_terms or None)
        f32 = jnp.float32
        parts = [
            dec.a_safe.astype(f32),
            dec.lower.astype(f32),
            dec.upper.astype(f32),
            dec.viable.astype(f32),
            dec.nonfinite.astype(f32)[None],
            dec.conflict.astype(f32)[None],
        ]
        if impact is not None:
            unmet = SafeAcceleration.impact_unmet(dec)
            parts += [x.astype(f32)[None] for x in (dec.impact_cap, unmet, dec.impact_active)]
        return jnp.concatenate(parts)

    spec = jax.ShapeDtypeStruct((robot.n,), jnp.float32)
    mspec = jax.ShapeDtypeStruct((robot.n, robot.n), jnp.float32)
    jspec = jax.ShapeDtypeStruct((3, robot.n), jnp.float32)
    extra = () if impact is None else (mspec, jspec, jspec, jax.ShapeDtypeStruct((3,), jnp.float32))
    return decide, jax.jit(packed).lower(spec, spec, spec, spec, mspec, spec, spec, spec, *extra).compile()


class JointLimitShieldWrapper(gymnasium.Wrapper, gymnasium.utils.RecordConstructorArgs):
    """Shield the joints of a Gymnasium ``MujocoEnv``; see the module docstring. Its arguments are recorded in
    ``env.spec`` (``gymnasium.make(env.spec)`` rebuilds the shielded env; Gymnasium's ``check_env`` needs it).

    Args:
      env: a Gymnasium env (possibly wrapped, e.g. by ``gymnasium.make``) whose ``unwrapped`` has
        ``model`` (``mujoco.MjModel``), ``data``, ``do_simulation`` and ``frame_skip``.
      joints: names of the shielded joints (default: every hinge/slide joint an actuator drives).
      v_max, a_max, j_max: limits [rad/s, rad/s^2, rad/s^3 or m/...], scalar or per joint
        (``Robot.from_model``: else the MJCF numerics, else ``a_max`` torque-derived; ``v_max`` is
        required unless the MJCF has it).
      method: ``"viability"``, ``"jerk"``, ``"naive"`` or ``"none"`` (``joint_shield.METHODS``).
      torque_limits: decide among the accelerations the actuators can realise (``SafeAcceleration``).
      correct_contacts: where a contact would push a substep's realised acceleration out of the bounds, give
        the actuators the torque that holds it at their edge (``actuation`` module docstring; one more
        constraint solve in the substeps with contacts); counted in ``contact_corrected``.
      start_inside: move the env's initial pose (``init_qpos``) inside the shielded joints' ranges, shrunk by the env's
        reset noise (``_move_start_inside``): Gymnasium's Ant starts its ankles 0.52 rad outside their ranges, Hopper
        and Walker2d their hips and knees at their upper limits plus noise, states no shield can answer for.
        Without it such a start is warned about once and counted (``reset``).
      impact: ``None`` or an ``ImpactPoint`` (``envs/impact_point.py``): the impact-aware speed cap on that point's
        approach speed along its normal, one more row of the decision; ``info["shield"]`` gets ``impact_cap``
        [m/s], ``impact_infeasible`` (no command inside the bounds and the torques met it), ``impact_speed``
        (the point's largest approach speed over the step's substeps [m/s]) and ``impact_active`` (the cap applied:
        ``ImpactPoint.surface`` given, only near it); and its strikes, measured at every substep
        (``envs/strike_record.py``): ``info["violation"]["impact"]`` (a strike's measured impulsive joint torque over
        ``tau_imp_max``, less 1, in the step its window closes), ``info["shield"]`` ``strike`` (1.0 then),
        ``strike_ratio``, ``strike_speed`` (its approach speed [m/s]) and ``strike_cap_unmet`` (1.0 then if the
        enforced cap was not delivered in the step the strike began in, before its contact, or the one before: unmet,
        or an actuator saturated; outside the cap's claim). In a
        strike (its first substep and its open window) an enforced cap turns the contact correction off: the velocity jump is the cap's to bound, and holding
        the acceleration in the bounds would push the point on into the surface.
      robot_kwargs: passed to ``Robot.from_model`` (``torque_margin``, ``torque_samples``, ...).

    Attributes:
      robot: the ``Robot`` (``n`` shielded joints). actuation: the ``CActuation``. impact: the
        ``impact_point.ImpactModel`` or ``None``.
      decide: the ``SafeAcceleration`` for ``frame_skip`` substeps.
      a_prev: ``(n,)`` float32, the last step's ``a_safe`` (zeros after ``reset``; ``"jerk"`` uses it).
      tally: running totals over the steps since construction (``reset_tally()`` zeroes them): counts
        ``steps``, ``position_violations``, ``velocity_violations``, ``torque_violations`` (steps with
        a positive excess), ``saturated``, ``nonfinite``, ``nonviable``, ``constrained``, ``disturbed``
        (steps with ``info["shield"]["disturbance"]``), and
        the largest ``max_position_excess`` [rad or m], ``max_velocity_excess`` [rad/s or m/s],
        ``max_torque_excess`` [N m or N], ``max_accel_error`` [rad/s^2], ``max_intervention`` [rad/s^2],
        and ``beyond_bounds``, ``contact_corrected`` (steps) with their largest values (``max_*``), and
        ``starts_outside`` (resets whose state lay outside the limits, ``reset``); with ``impact``,
        ``impact_infeasible`` (steps), ``max_impact_speed`` [m/s], ``impact_violations``, ``max_impact_excess``,
        ``strikes`` and ``max_strike_ratio``.
      violations: the kinds ``info["violation"]`` holds: ``VIOLATIONS``, ``"jerk"`` where the robot has ``j_max``, and
        ``"impact"`` with an impact point.

    Raises ``TypeError`` for an env that is not a MuJoCo env, ``ValueError`` (from ``Robot.from_model``
    / ``SafeAcceleration``) naming the joint, actuator or field that is missing or unsupported.
    """

    def __init__(
        self,
        env: gymnasium.Env,
        joints=None,
        v_max=None,
        a_max=None,
        j_max=None,
        method: str = "viability",
        torque_limits: bool = True,
        correct_contacts: bool = True,
        start_inside: bool = False,
        impact: ImpactPoint | None = None,
        **robot_kwargs,
    ):
        check_not_forked_from_jax("JointLimitShieldWrapper")  # before any JAX call (fork_guard)
        gymnasium.utils.RecordConstructorArgs.__init__(
            self,
            joints=joints,
            v_max=v_max,
            a_max=a_max,
            j_max=j_max,
            method=method,
            torque_limits=torque_limits,
            correct_contacts=correct_contacts,
            start_inside=start_inside,
            impact=impact,
            **robot_kwargs,
        )
        gymnasium.Wrapper.__init__(self, env)
        if impact is not None and not isinstance(impact, ImpactPoint):
            raise TypeError(f"impact must be None or an ImpactPoint, got {type(impact).__name__}")
        base = env.unwrapped
        self.torque_limits = bool(torque_limits) and method != "none"
        self.correct_contacts = bool(correct_contacts) and method != "none"
        missing = [name for name in _REQUIRED if not hasattr(base, name)]
        if missing or not isinstance(base.model, mujoco.MjModel) or not isinstance(base.data, mujoco.MjData):
            raise TypeError(
                "JointLimitShieldWrapper wraps a Gymnasium MujocoEnv (model: MjModel, data: MjData, do_simulation, "
                f"frame_skip); got {type(base).__module__}.{type(base).__name__}"
                + (f" without {missing}" if missing else " whose model/data are not MjModel/MjData")
            )
        if "_shielded_by" in vars(base):
            raise ValueError("this env is already shielded (one JointLimitShieldWrapper per env)")
        if isinstance(base, MujocoEnv) and type(base).do_simulation is not MujocoEnv.do_simulation:
            raise ValueError(
                f"{type(base).__name__} overrides MujocoEnv.do_simulation, the physics call the shield takes over: "
                "its own code would not run under the shield. Move that code into the env's step (around "
                "do_simulation), or shield an env that keeps Gymnasium's do_simulation"
            )
        robot_kwargs.setdefault("control_dt", float(base.model.opt.timestep) * int(base.frame_skip))
        self.robot = rob = Robot.from_model(base.model, joints, v_max, a_max, j_max, **robot_kwargs)
        self.actuation = CActuation(rob, base.model)
        self.method = method
        # with method "none" SafeAcceleration refuses the cap (the decider is built below)
        self.impact = None if impact is None else impact.resolve(base.model, rob)
        self._base = base
        self._robot_key = rob.fingerprint()
        self._deciders = {}  # n_frames -> (SafeAcceleration, compiled XLA executable); shared: _SHARED_DECIDERS
        self.decide = self._decider(int(base.frame_skip))[0]  # validates and compiles eagerly
        n = rob.n
        self._n = n
        self._nu = int(base.model.nu)
        self._qadr = as_slice(rob.qpos_adr)  # a slice when contiguous: views instead of fancy-index copies
        self._dofs = as_slice(rob.dof_adr)
        self._shielded_act = np.zeros(self._nu, bool)
        self._shielded_act[rob.actuator_ids] = True
        lim = rob.limits
        # the model's own limits; +-inf for unlimited joints: no position excess
        self._q_lo = np.where(rob.limited, np.asarray(lim.q_min, np.float64), -np.inf)
        self._q_hi = np.where(rob.limited, np.asarray(lim.q_max, np.float64), np.inf)
        self._v_max = np.broadcast_to(np.asarray(lim.v_max, np.float64), (n,)).copy()
        self._h = float(rob.timestep)
        # an RK4 substep is retaken beyond RK4_RESTEP RK4_MARGIN v_max / dt [rad/s^2] (dt = h n_frames)
        self._rk4_tol = RK4_RESTEP * RK4_MARGIN * self._v_max / self._h
        # solver roundoff at the bounds is not counted as a contact correction
        self._correct_tol = BOUNDS_TOL * np.broadcast_to(np.asarray(lim.a_max, np.float64), (n,))
        self._joint_ids = np.asarray(rob.joint_ids)
        self._jtf = np.zeros(int(base.model.nv))  # J^T f buffer of ``_disturbed``
        self.a_prev = np.zeros(n, np.float32)
        # the kinds of info["violation"]: the strikes' impulsive joint torque too where an impact point names what
        # strikes (measured per substep, envs/strike_record.py)
        self.violations = VIOLATIONS + (("jerk",) if lim.j_max is not None else ())
        self.violations += ("impact",) if self.impact is not None else ()
        self._strike = None if self.impact is None else strike_record.fresh(n, xp=np)
        self._efc_contact = np.zeros(0)  # the contact rows' forces (buffer of ``_contact_joint_force``)
        self.tally = _zero_tally(self.violations)
        self._records = []
        self._bufs = {}
        self._brake = False  # brake_on_next_step
        self._warned_start = False
        if start_inside:
            self._move_start_inside()
        base._shielded_by = self
        base.do_simulation = self._do_simulation  # the one thing taken over (an instance attribute)

    def _move_start_inside(self) -> None:
        """``start_inside``: every limited shielded joint's ``init_qpos`` (the pose ``MujocoEnv.reset_model`` adds its
        noise to) clipped into its range shrunk by the env's reset noise (``_reset_noise_scale``, uniform about
        ``init_qpos`` in Gymnasium's locomotion envs; 0 where the env has none) and 1 % of the range."""
        base = self._base
        if not hasattr(base, "init_qpos"):
            raise TypeError(f"start_inside=True moves the env's init_qpos; {type(base).__name__} has none")
        base.init_qpos[:] = self.robot.pose_inside(base.init_qpos, getattr(base, "_reset_noise_scale", 0.0))

    def _limit_excess(self, q, v):
        """``(position, velocity)`` excess over the model's own limits per joint, ``(..., n)`` each [rad or m, rad/s or
        m/s], negative inside (unlimited joints: ``-inf`` position excess)."""
        return np.maximum(q - self._q_hi, self._q_lo - q), np.abs(v) - self._v_max

    def _start_violation(self) -> dict:
        """The reset state's excess over the model's limits: ``{"position", "velocity"}`` [rad or m, rad/s or m/s]
        of the shielded joints, 0.0 inside; the first one found outside is warned about, once per wrapper."""
        d = self._base.data
        q, v = d.qpos[self._qadr], d.qvel[self._dofs]
        pos_ex, vel_ex = self._limit_excess(q, v)
        out = {"position": max(float(pos_ex.max()), 0.0), "velocity": max(float(vel_ex.max()), 0.0)}
        if (out["position"] > 0.0 or out["velocity"] > 0.0) and not self._warned_start:
            self._warned_start = True
            i = int(np.argmax(np.maximum(pos_ex, vel_ex)))
            where = (
                f"q = {q[i]:.4g} outside [{self._q_lo[i]:.4g}, {self._q_hi[i]:.4g}]"
                if pos_ex[i] >= vel_ex[i]
                else f"|v| = {abs(v[i]):.4g} over v_max {self._v_max[i]:.4g}"
            )
            warnings.warn(
                f"the env's reset state lies outside the shielded joints' limits (joint {self.robot.names[i]!r}: "
                f"{where}): no guarantee holds until the joints are back inside (the shield brakes toward the "
                "range; counted as non-viable and in tally['starts_outside']); start_inside=True moves the env's "
                "initial pose inside",
                stacklevel=3,
            )
        return out

    # ---- the decision ------------------------------------------------------------------------------
    def _decider(self, n_frames: int):
        """``(SafeAcceleration, compiled)`` for ``n_frames`` substeps. ``compiled(q, v, a_des, a_prev, M_ss, f_s,
        tau_lo, tau_hi)`` takes float32 arrays (the state, the command, the previous acceleration and the
        ``TorqueModel``) and returns one packed ``(4 n + 2,)`` float32 array ``[a_safe, lower, upper, viable,
        nonfinite, torque_conflict]`` (one device-to-host transfer).

        Cached per wrapper and shared between wrappers whose robots are alike (``Robot.fingerprint``) with the
        same method, torque limits and ``n_frames``: a vector env of ``N`` copies of one env traces and compiles
        the decision once, not ``N`` times (~10 s each here)."""
        hit = self._deciders.get(n_frames)
        if hit is None:
            impact_key = None if self.impact is None else self.impact.key()
            key = (self._robot_key, self.method, self.torque_limits, int(n_frames), impact_key)
            hit = _SHARED_DECIDERS.get(key)
            if hit is None:
                hit = _compile_decider(self.robot, int(n_frames), self.method, self.torque_limits, self.impact)
                _SHARED_DECIDERS.put(key, hit)
            self._deciders[n_frames] = hit
        return hit

    # ---- the physics call --------------------------------------------------------------------------
    def _do_simulation(self, ctrl, n_frames) -> None:
        """Replaces ``MujocoEnv.do_simulation``: ``n_frames`` substeps with the shielded joints' acceleration
        held at ``a_safe``; ``ctrl`` ``(nu,)`` the env's actuator commands. See the module docstring."""
        base, act, n = self._base, self.actuation, self._n
        m, d = base.model, base.data
        ctrl = np.array(ctrl, dtype=np.float64)  # a copy: cleaned below
        if ctrl.shape != (self._nu,):
            raise ValueError(f"Action dimension mismatch. Expected {(self._nu,)}, found {ctrl.shape}")
        n_frames = int(n_frames)
        decide, compiled = self._decider(n_frames)
        bad = ~(np.abs(ctrl) <= MJ_MAXVAL)
        bad_in = bool(bad.any())
        shielded_bad = False
        if bad_in:
            shielded_bad = bool(bad[self._shielded_act].any())
            ctrl[bad] = 0.0

        dofs, qadr = self._dofs, self._qadr
        Q, V, C, TE, S = self._buffers(n_frames)
        a_des, M, f = act.smooth_stage(d, ctrl)
        if shielded_bad or self._brake:
            a_des = np.full(n, np.nan)
        tm = act.torque_model(d, M, f, self._h * n_frames)
        f32 = np.float32
        imp = self.impact
        impact_terms = () if imp is None else imp.c_terms(m, d, dofs)
        out = compiled(
            d.qpos[qadr].astype(f32),
            d.qvel[dofs].astype(f32),
            a_des.astype(f32),
            self.a_prev,
            *(x.astype(f32) for x in tm),
            *(x.astype(f32) for x in impact_terms),
        )
        out = np.asarray(out)
        a_prev, self.a_prev = self.a_prev, out[:n]  # a fresh host array per call
        a_safe = out[:n].astype(np.float64)
        # no command inside the bounds and torques met the impact cap; the strike record's flag where it is enforced
        # (a measured-only point has no cap to be unmet)
        infeasible = imp is not None and bool(out[4 * n + 3] > 0.5)
        cap_unmet = infeasible and imp.enforce
        lower, upper = out[n : 2 * n].astype(np.float64), out[2 * n : 3 * n].astype(np.float64)
        # every substep's realised acceleration is kept inside the decision's bounds (a contact corrected)
        band = None if not self.correct_contacts else (np.minimum(lower, a_safe), np.maximum(upper, a_safe))

        rk4_tol = self._rk4_tol / n_frames
        V[0] = d.qvel[dofs]
        corrected = 0.0
        disturbed = False
        speed = -np.inf
        if imp is not None:  # the strike record this call starts from (re-armed after a closed strike)
            kept = self._strike
            strike0 = strike_record.start_step(kept, strike_record.fresh(n, xp=np), False, np)
            strike, touched = strike0, False
        for k in range(n_frames):
            if k:
                _, M, f = act.smooth_stage(d, ctrl, want_a_des=False)
            band_k = band
            if imp is not None:  # the point's approach speed at the substep's start, and whether it touches
                J = impact_terms[1] if k == 0 else imp.c_jacobian(m, d, dofs)
                w0 = float(imp.normal @ (J @ d.qvel[dofs]))
                speed = max(speed, w0)
                touch = imp.c_striking(d)
                touched |= touch
                if imp.enforce and strike_record.in_strike(strike, touch):
                    band_k = None  # in a strike the jump is the cap's to bound (as JointLimitShield)
                q0, v0 = d.qpos[qadr].copy(), d.qvel[dofs].copy()
            inv, out_k = act.finish_substep(d, M, f, a_safe, band_k, rk4_tol)
            if imp is not None:
                strike, _ = strike_record.advance(
                    strike,
                    np.bool_(touch),
                    w0,
                    float(imp.normal @ (J @ d.qvel[dofs])),
                    q0,
                    v0,
                    self._contact_joint_force(m, d),
                    self._h,
                    imp.window_substeps,
                    imp.stop_fraction,
                    np,
                    cap_unmet=cap_unmet,
                    saturated=bool(inv.saturated.any()) and imp.enforce,  # the cap decided, not realised
                )
            if out_k is not None:
                out_k = np.abs(out_k)
                corrected = max(corrected, float(np.max(out_k, where=out_k > self._correct_tol, initial=0.0)))
            Q[k] = d.qpos[qadr]
            V[k + 1] = d.qvel[dofs]
            C[k] = d.qfrc_constraint[dofs]
            if not disturbed and C[k].any():  # a nonzero (or NaN) constraint force
                disturbed = self._disturbed(m, d)
            TE[k] = inv.torque_excess
            S[k] = inv.saturated
        mujoco.mj_rnePostConstraint(m, d)

        # reductions over the substeps, once per call
        pos_ex, vel_ex = self._limit_excess(Q, V[1:])
        pos, vel = max(float(pos_ex.max()), 0.0), max(float(vel_ex.max()), 0.0)
        accel_error = float(np.abs((V[1:] - V[:-1]) / self._h - a_safe).max())
        finite = np.isfinite(a_des)
        if finite.all():
            intervention = float(np.abs(a_safe - a_des).max())
        else:
            intervention = float(np.max(np.abs(a_safe - a_des), where=finite, initial=0.0))
        self._records.append(
            {
                "position": pos,
                "velocity": vel,
                "torque": float(TE.max()),
                "intervention": intervention,
                "saturated": bool(S.any()),
                "nonfinite": bad_in or self._brake or bool(out[4 * n] > 0.5),
                "viable": bool((out[3 * n : 4 * n] > 0.5).all()),
                "torque_conflict": bool(out[4 * n + 1] > 0.5),
                "constrained": bool(C.any()),
                "disturbance": disturbed,
                "accel_error": accel_error,
                "contact_corrected": corrected,
                "a_des": a_des,
                "a_safe": a_safe,
                "lower": lower,
                "upper": upper,
                "beyond_bounds": max(float(np.maximum(a_safe - upper, lower - a_safe).max()), 0.0),
            }
        )
        if "jerk" in self.violations:
            self._records[-1]["jerk"] = float(decide.jerk_excess(self.a_prev, a_prev, np))
        if imp is not None:
            cap, active = float(out[4 * n + 2]), bool(out[4 * n + 4] > 0.5)
            self._strike, fig = strike_record.finish(
                strike0, strike, touched, imp.dt_impact, imp.tau_imp_max, np, cap_unmet=cap_unmet
            )
            self._records[-1].update(
                impact_cap=cap,
                impact_infeasible=infeasible,
                impact_speed=speed,
                impact_active=active,
                impact=float(fig["excess"]),
                strike=float(fig["strike"]),
                strike_ratio=float(fig["ratio"]),
                strike_speed=float(fig["speed"]),
                strike_cap_unmet=float(fig["cap_unmet"]),
            )

    def _rows_joint_force(self, m, d, rows) -> np.ndarray:
        """``(n,)`` ``J^T f`` on the shielded dofs over the constraint rows ``rows`` (``(nefc,)`` bool) of this
        substep's solve [N m or N] (a view of a reused buffer)."""
        mujoco.mj_mulJacTVec(m, d, self._jtf, np.where(rows, d.efc_force[: d.nefc], 0.0))
        return self._jtf[self._dofs]

    def _contact_joint_force(self, m, d) -> np.ndarray:
        """``(n,)`` the contacts' joint force on the shielded dofs in this substep's constraint solve [N m or N]
        (the contact rows; the joint-limit rows left out), as ``JointLimitShield`` measures it."""
        if d.nefc == 0:
            return np.zeros(self._n)
        contact = d.efc_type[: d.nefc] >= int(mujoco.mjtConstraint.mjCNSTR_CONTACT_FRICTIONLESS)
        return self._rows_joint_force(m, d, contact).copy()

    def _disturbed(self, m, d) -> bool:
        """Did a constraint force other than the shielded joints' own limit rows act on a shielded dof this
        substep (``J^T f`` on the shielded dofs with those rows left out)? MuJoCo's joint-limit rows act only
        past a limit (margin 0; under RK4 at a stage past it): counting them would excuse the overshoot that
        set them off. What remains is a contact, an equality, a tendon limit, friction loss: a disturbance
        the bounds do not model (the evaluator's ``disturbance``)."""
        n = d.nefc
        own = (d.efc_type[:n] == mujoco.mjtConstraint.mjCNSTR_LIMIT_JOINT) & np.isin(d.efc_id[:n], self._joint_ids)
        if not own.any():
            return True
        return bool(np.any(self._rows_joint_force(m, d, ~own) != 0.0))

    def _buffers(self, n_frames: int):
        """Per-substep records, reused (cached per ``n_frames``): positions ``Q (n_frames, n)``, velocities
        ``V (n_frames + 1, n)`` (``V[0]`` the step's start), the constraint force on the shielded dofs
        ``C``, torque excess ``TE`` and saturation ``S`` ``(n_frames, n)``."""
        buf = self._bufs.get(n_frames)
        if buf is None:
            n = self._n
            e = np.empty
            buf = self._bufs[n_frames] = (
                e((n_frames, n)),
                e((n_frames + 1, n)),
                e((n_frames, n)),
                e((n_frames, n)),
                e((n_frames, n), bool),
            )
        return buf

    # ---- Gymnasium interface -----------------------------------------------------------------------
    def reset(self, *, seed=None, options=None):
        """``env.reset``; zeroes ``a_prev``; re-reads the actuators' values from the model (``CActuation.refresh``: a
        domain randomisation that changed the model before this reset). ``info["start_violation"]``: ``{"position",
        "velocity"}``, the reset state's excess over the shielded joints' limits (0.0 inside; outside, no guarantee
        holds until the joints are back inside: warned once, counted in ``tally["starts_outside"]``;
        ``start_inside=True`` moves the env's initial pose inside)."""
        self.a_prev = np.zeros(self._n, np.float32)
        self._records = []
        if self.impact is not None:  # an episode's strikes are measured afresh
            self._strike = strike_record.fresh(self._n, xp=np)
        obs, info = self.env.reset(seed=seed, options=options)
        self.actuation.refresh()
        info = dict(info)
        info["start_violation"] = start = self._start_violation()
        self.tally["starts_outside"] += start["position"] > 0.0 or start["velocity"] > 0.0
        return obs, info

    def step(self, action):
        """``env.step(action)`` with ``info["violation"]`` and ``info["shield"]`` added (module docstring).

        ``info["violation"]``: ``{"position", "velocity", "torque"}`` -> float, the largest excess over the
        step's substeps [rad or m, rad/s or m/s, N m or N], 0.0 when none; ``"jerk"`` too where the robot has
        ``j_max`` (``max |a_safe - a_prev| - j_max dt`` [rad/s^2], float32, as the Brax shield's), ``"impact"`` with an
        impact point (``violations``). ``info["shield"]``:
        ``intervention`` (``max |a_safe - a_des|`` over the finite entries [rad/s^2]), ``saturated``,
        ``nonfinite``, ``viable``, ``constrained``, ``torque_conflict`` (bools; ``constrained``: a contact or
        limit force acted on a shielded dof in some substep; ``disturbance``: one other than the shielded
        joints' own limit rows did, a contact mostly, ``_disturbed``; ``torque_conflict``: no acceleration inside the
        bounds' position/velocity/viability terms was realisable at the step's start, see ``SafeAcceleration``),
        ``beyond_bounds`` (how far ``a_safe`` left ``[lower, upper]`` [rad/s^2]: the acceleration or jerk limit
        given way where no acceleration inside it was realisable), ``contact_corrected`` (how far a contact
        would have pushed a substep's realised acceleration out of ``[lower, upper]`` [rad/s^2] before the
        actuators were given the torque to hold it there; ``actuation`` module docstring), ``accel_error``
        (``max |(v+ - v)/h - a_safe|`` [rad/s^2]), and ``a_des``, ``a_safe``, ``lower``, ``upper``: ``(n,)``
        float64 [rad/s^2]. If the env's step runs the physics several times, the maxima/any over them
        (arrays: the last).
        """
        self._records = []
        try:
            obs, reward, terminated, truncated, info = self.env.step(action)
        finally:
            self._brake = False
        recs, self._records = self._records, []
        if not recs:
            raise RuntimeError("the wrapped env's step did not call do_simulation")
        rec = dict(recs[-1])
        for r in recs[:-1]:
            if "jerk" in rec:
                rec["jerk"] = max(rec["jerk"], r["jerk"])
            for k in (
                "position",
                "velocity",
                "torque",
                "intervention",
                "accel_error",
                "beyond_bounds",
                "contact_corrected",
            ):
                rec[k] = max(rec[k], r[k])
            for k in ("saturated", "nonfinite", "constrained", "disturbance", "torque_conflict"):
                rec[k] = rec[k] or r[k]
            if self.impact is not None:
                rec["impact"] = max(rec["impact"], r["impact"])
                rec["strike"] += r["strike"]
                rec["strike_ratio"] = max(rec["strike_ratio"], r["strike_ratio"])
                rec["strike_speed"] = max(rec["strike_speed"], r["strike_speed"])
                rec["strike_cap_unmet"] = max(rec["strike_cap_unmet"], r["strike_cap_unmet"])
                rec["impact_cap"] = min(rec["impact_cap"], r["impact_cap"])
                rec["impact_speed"] = max(rec["impact_speed"], r["impact_speed"])
                rec["impact_infeasible"] = rec["impact_infeasible"] or r["impact_infeasible"]
                rec["impact_active"] = rec["impact_active"] or r["impact_active"]
            rec["viable"] = rec["viable"] and r["viable"]
        info = dict(info)
        info["violation"] = {k: rec[k] for k in self.violations}
        info["shield"] = {k: v for k, v in rec.items() if k not in self.violations}
        t = self.tally
        t["steps"] += 1
        for k in self.violations:
            t[f"{k}_violations"] += rec[k] > 0.0
            t[f"max_{k}_excess"] = max(t[f"max_{k}_excess"], rec[k])
        t["saturated"] += rec["saturated"]
        t["nonfinite"] += rec["nonfinite"]
        t["nonviable"] += not rec["viable"]
        t["constrained"] += rec["constrained"]
        t["disturbed"] += rec["disturbance"]
        t["torque_conflict"] += rec["torque_conflict"]
        t["max_accel_error"] = max(t["max_accel_error"], rec["accel_error"])
        t["max_intervention"] = max(t["max_intervention"], rec["intervention"])
        t["beyond_bounds"] += rec["beyond_bounds"] > 0.0
        t["max_beyond_bounds"] = max(t["max_beyond_bounds"], rec["beyond_bounds"])
        t["contact_corrected"] += rec["contact_corrected"] > 0.0
        t["max_contact_corrected"] = max(t["max_contact_corrected"], rec["contact_corrected"])
        if self.impact is not None:
            t["impact_infeasible"] += rec["impact_infeasible"]
            t["max_impact_speed"] = max(t["max_impact_speed"], rec["impact_speed"])
            t["strikes"] += rec["strike"]
            t["max_strike_ratio"] = max(t["max_strike_ratio"], rec["strike_ratio"])
        return obs, reward, terminated, truncated, info

    def brake_on_next_step(self) -> None:
        """Substitute braking for the command of the next ``step`` (a ``NonFiniteActionGuardWrapper`` outside
        replaced a non-finite action by zeros); counted as ``nonfinite``."""
        self._brake = True

    def reset_tally(self) -> None:
        """Zero ``tally``."""
        self.tally = _zero_tally(self.violations)
