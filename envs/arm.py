"""MJX robot-arm reach environments with joint-acceleration actions (Brax ``Env`` contract).

An action is a joint acceleration command ``a`` [rad/s^2] (``step``: ``action in [-1, 1]^n`` scaled
by ``limits.a_max``; ``step_acc``: ``a`` directly). It is realised by inverse dynamics at *every*
physics substep: ``tau = M(q) a + qfrc_bias(q, v) - qfrc_passive(q, v)`` is applied through the
torque motors (gear 1), which MuJoCo clamps to their ``ctrlrange`` (the torque limits), and the
model's own integrator (Euler or implicitfast, read from the MJCF) advances the state. So a
command the motors can deliver is followed to float32 roundoff, and one they cannot is not; both
are measured each step (``metrics['accel_error']``, ``metrics['violation/torque']``).

MuJoCo's joint-limit constraint is disabled at simulation time (``mjDSBL_LIMIT``; the ranges stay
in the model and are read from it), and contacts are off: nothing hides an overshoot, which is
measured at every substep (``metrics['violation/position']``).

All limits come from the MJCF (see ``assets/README.md``): position = joint ``range``, torque =
motor ``ctrlrange``, velocity/acceleration/jerk and the substep count = custom numerics. The
acceleration limit is then lowered, if needed, to the torque-derived one (``torque_scale``): the
largest uniform scaling of the nominal ``a_max`` box for which every acceleration in the box needs
no more than the torque limits at every sampled state (a conservative variant of Del Prete's
Alg. 4), so that the shielded commands are realisable.
"""

from __future__ import annotations

import functools
import pathlib
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxlimits.envs import mjx_stages

with warnings.catch_warnings():  # brax imports jaxopt, which warns that it is unmaintained
    warnings.simplefilter("ignore", DeprecationWarning)
    from brax.envs.base import Env, State, Wrapper  # noqa: F401 (Wrapper: re-exported for the wrappers)

import jaxlimits as jl
import jaxlimits.torque as _torque

ASSETS = pathlib.Path(__file__).parent / "assets"
PRECISION_SCALE = 0.05  # [m], length scale of the optional precision reward (ArmReach(precision_reward=w))
IK_DAMPING = 0.05  # [m], damping of the optional IK observation (ArmReach(ik_observation=True))
# "impact": a strike whose measured impulsive joint torque exceeds its bound (WallStrike; 0 without contacts)
VIOLATION_KEYS = ("position", "velocity", "acceleration", "jerk", "torque", "impact")
_SEMI_IMPLICIT = (mujoco.mjtIntegrator.mjINT_EULER, mujoco.mjtIntegrator.mjINT_IMPLICITFAST)


def _mjx_tracing(fn):
    """Trace ``fn`` as the envs' physics must be traced: NumPy rank promotion allowed (MJX's own code relies
    on it; tests raise on it) and float32 matrix products in full float32 (``jax.default_matmul_precision
    ("highest")``, read when each product is traced). On a GPU JAX's default for float32 products is TF32
    (a 10-bit mantissa): measured on an H200, the servo Panda's realised acceleration then missed the
    commanded one by up to 0.14 rad/s^2 (7.7e-4 in full float32) and a PPO run had 55 position-violating
    steps in 3.3 M (max 3.2e-4 rad). On a CPU float32 products are full float32 either way."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.numpy_rank_promotion("allow"), jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped


def _numeric(mjm: mujoco.MjModel, name: str, n: int | None = None) -> np.ndarray | None:
    idx = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    if idx < 0:
        return None
    adr, size = mjm.numeric_adr[idx], mjm.numeric_size[idx]
    out = np.array(mjm.numeric_data[adr : adr + size], dtype=np.float64)
    if n is not None and out.shape != (n,):
        raise ValueError(f"custom numeric {name!r} must have {n} values, got {out.shape}")
    return out


def damped_ls_step(J, err):
    """Damped least-squares joint step ``J^T (J J^T + lam^2 I)^-1 err`` [rad], ``(n,)``, ``lam = IK_DAMPING``.

    ``J`` ``(3, n)`` [m/rad] the end-effector position Jacobian, ``err`` ``(3,)`` [m] the target minus the
    end effector. Finite and bounded (``<= |err| / (2 lam)``) at singularities."""
    return J.T @ jnp.linalg.solve(J @ J.T + IK_DAMPING**2 * jnp.eye(3, dtype=J.dtype), err)


def reach_reward(dist, precision_reward: float):
    """A reach's reward ``-d + w (1 - tanh(d / PRECISION_SCALE))`` for end-effector distance ``d`` [m]
    and precision weight ``w >= 0`` (``w = 0``: plain ``-d``)."""
    return -dist + precision_reward * (1.0 - jnp.tanh(dist / PRECISION_SCALE))


def load_arm(xml_path) -> mujoco.MjModel:
    """Load an arm MJCF and check the conventions the envs rely on (hinges; motor i drives joint i)."""
    mjm = mujoco.MjModel.from_xml_path(str(xml_path))
    n = mjm.njnt
    if mjm.nq != n or mjm.nv != n or np.any(mjm.jnt_type != mujoco.mjtJoint.mjJNT_HINGE):
        raise ValueError(f"{xml_path}: expected {n} hinge joints only")
    if mjm.nu != n or np.any(mjm.actuator_trnid[:, 0] != np.arange(n)) or np.any(mjm.actuator_gear[:, 0] != 1.0):
        raise ValueError(f"{xml_path}: expected one gear-1 motor per joint, in joint order")
    if not np.all(mjm.jnt_limited) or not np.all(mjm.actuator_ctrllimited):
        raise ValueError(f"{xml_path}: every joint needs a range and every motor a ctrlrange")
    if mjm.opt.integrator not in _SEMI_IMPLICIT:
        raise ValueError(
            f"{xml_path}: integrator must be Euler or implicitfast (semi-implicit), got {mjm.opt.integrator}"
        )
    if np.any(mjm.dof_damping != 0) or np.any(mjm.jnt_stiffness != 0):
        raise ValueError(
            f"{xml_path}: joint damping and stiffness must be 0 (commanded accelerations are realised exactly)"
        )
    return mjm


def sample_states(rng: np.random.Generator, q_min, q_max, v_max, n_samples: int):
    """Uniform positions; velocities uniform for half the samples and at the box's vertices for the rest.

    The bias forces are quadratic in ``v``, so their worst case lies at a vertex of the velocity box,
    which uniform sampling in 7 dimensions almost never reaches.
    """
    n = len(q_min)
    q = rng.uniform(q_min, q_max, size=(n_samples, n))
    v = rng.uniform(-1.0, 1.0, size=(n_samples, n))
    half = n_samples // 2
    v[half:] = np.sign(v[half:])
    return q, v * v_max


def dynamics_c(mjm: mujoco.MjModel, q: np.ndarray, v: np.ndarray):
    """``M(q)`` and ``h(q, v) = qfrc_bias - qfrc_passive`` from MuJoCo's C functions, looped in Python.

    Uses ``mj_kinematics``/``mj_comPos``/``mj_crb`` + ``mj_fullM`` for ``M`` and ``mj_rne`` (no
    acceleration term) for ``h``, per sample; the reference the benchmark compares Alg. 4 with.
    """
    d = mujoco.MjData(mjm)
    n, N = mjm.nv, q.shape[0]
    M = np.zeros((N, n, n))
    h = np.zeros((N, n))
    for i in range(N):
        d.qpos[:] = q[i]
        d.qvel[:] = v[i]
        mujoco.mj_kinematics(mjm, d)
        mujoco.mj_comPos(mjm, d)
        mujoco.mj_crb(mjm, d)
        mujoco.mj_fullM(mjm, d, M[i])
        mujoco.mj_comVel(mjm, d)
        mujoco.mj_rne(mjm, d, 0, h[i])
    return M, h


class ArmReach(Env):
    """Reach a random target with the end effector; actions are joint accelerations.

    Args:
      xml_path: the arm's MJCF (see ``load_arm`` for its conventions).
      ee_site: name of the end-effector site.
      target_low, target_high: corners of the box targets are drawn from [m].
      torque_samples: states sampled for the torque-derived ``a_max`` (0 keeps the nominal one, the
        datasheet's: ``torque_margin`` is then not applied).
      torque_margin: ``a_max = min(1, torque_margin * s) * a_nominal`` with ``s`` the worst sampled
        ``box_scale``. Sampling underestimates the worst case (Panda: s = 0.256 over 2e4 samples,
        0.218 over 1e6), hence 0.8; the torque-violation metric checks the outcome.
      reset_margin: initial positions are uniform in the range shrunk by this fraction at each end.
      start: ``"random"`` (initial positions uniform in the shrunk range) or ``"home"`` (the model's
        keyframe ``home`` with every joint scaled by a factor uniform in ``home_scale``, clipped to the
        shrunk range: Isaac Lab's ``reset_joints_by_scale`` of its Reach-Franka task); see ``reset``.
      home_scale: ``(low, high)`` of that factor.
      target: ``"reachable"`` (targets are end-effector positions of random configurations inside
        the limits) or ``"box"`` (uniform in ``[target_low, target_high]``); see ``reset``.
      ik_observation: append the damped least-squares joint step toward the target,
        ``J^T (J J^T + lam^2 I)^-1 (target - ee)`` [rad] with ``lam = IK_DAMPING`` [m] and ``J`` the
        end-effector position Jacobian (``mjx.jac``), to the observation (``n`` more entries). It is
        a function of the observed state (no extra information), but it saves the policy from
        learning the arm's kinematics: with velocity actions a reach policy becomes nearly linear.
      precision_reward: weight ``w`` of a precision term: the reward is
        ``-d + w (1 - tanh(d / PRECISION_SCALE))`` with ``d`` the end-effector distance [m]
        (``w = 0``: plain ``-d``). The plain distance barely distinguishes 3 cm from 8 cm; the term
        rewards arriving within a few centimetres (the evaluation's success radius).

    Attributes: ``limits`` (``jl.JointLimits``), ``tau_max`` (n,), ``dt`` (control period [s]),
    ``frame_skip`` (physics substeps per step), ``integrator`` (``"semi_implicit"``: what
    ``jl.acc_bounds`` must be told), ``mj_model`` (the MuJoCo model with limits enabled, for
    reading/rendering), ``sys`` (the MJX model used for simulation, limits disabled).
    """

    def __init__(
        self,
        xml_path,
        ee_site: str,
        target_low,
        target_high,
        torque_samples: int = 20000,
        torque_margin: float = 0.8,
        reset_margin: float = 0.1,
        seed: int = 0,
        target: str = "reachable",
        start: str = "random",
        home_scale=(0.5, 1.5),
        ik_observation: bool = False,
        precision_reward: float = 0.0,
    ):
        mjm = load_arm(xml_path)
        self.mj_model = mjm
        self.xml_path = pathlib.Path(xml_path)
        n = mjm.njnt
        self.n = n
        q_min, q_max = mjm.jnt_range[:, 0].copy(), mjm.jnt_range[:, 1].copy()
        v_max = _numeric(mjm, "jaxlimits_v_max", n)
        a_nom = _numeric(mjm, "jaxlimits_a_max", n)
        j_max = _numeric(mjm, "jaxlimits_j_max", n)
        skip = _numeric(mjm, "jaxlimits_frame_skip")
        if v_max is None or a_nom is None or skip is None:
            raise ValueError(
                f"{xml_path}: custom numerics jaxlimits_v_max, jaxlimits_a_max and jaxlimits_frame_skip are required"
            )
        self.frame_skip = int(skip[0])
        self.dt = float(mjm.opt.timestep) * self.frame_skip
        self.integrator = "semi_implicit"
        lo, hi = mjm.actuator_ctrlrange[:, 0], mjm.actuator_ctrlrange[:, 1]
        if not np.allclose(-lo, hi):
            raise ValueError(f"{xml_path}: torque limits (ctrlrange) must be symmetric")
        self.tau_max = hi.copy()
        self.a_max_nominal = a_nom
        scale = 1.0
        if torque_samples:
            qs, vs = sample_states(np.random.default_rng(seed), q_min, q_max, v_max, torque_samples)
            M, h = dynamics_c(mjm, qs, vs)
            scale = float(np.min(_torque.box_scale(M, h, self.tau_max, a_nom, xp=np)))
        self.torque_scale = scale
        a_max = a_nom * min(1.0, torque_margin * scale) if torque_samples else a_nom.copy()
        self.limits = jl.JointLimits(q_min, q_max, v_max, a_max, j_max)
        self.ee_site = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_SITE, ee_site)
        self.target_low = np.asarray(target_low, np.float32)
        self.target_high = np.asarray(target_high, np.float32)
        self.reset_margin = reset_margin
        if target not in ("reachable", "box"):
            raise ValueError(f"target must be 'reachable' or 'box', got {target!r}")
        self.target_mode = target
        if start not in ("random", "home"):
            raise ValueError(f"start must be 'random' or 'home', got {start!r}")
        self.start_mode = start
        self.home_qpos = None
        if start == "home":
            key = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_KEY, "home")
            if key < 0:
                raise ValueError(f"{xml_path}: start='home' needs a keyframe named 'home'")
            self.home_qpos = mjm.key_qpos[key].copy()
        lo_s, hi_s = (float(x) for x in home_scale)
        if not (np.isfinite(lo_s) and np.isfinite(hi_s) and lo_s <= hi_s):
            raise ValueError(f"home_scale must be finite (low, high) with low <= high, got {home_scale!r}")
        self.home_scale = (lo_s, hi_s)
        self.ik_observation = bool(ik_observation)
        if not (np.isfinite(precision_reward) and precision_reward >= 0):
            raise ValueError(f"precision_reward must be a finite number >= 0, got {precision_reward!r}")
        self.precision_reward = float(precision_reward)
        self._ee_body = int(mjm.site_bodyid[self.ee_site])
        sim = mujoco.MjModel.from_xml_path(str(xml_path))
        sim.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_LIMIT | mujoco.mjtDisableBit.mjDSBL_CONTACT
        sim.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP  # no damping: the Euler step is explicit in M^-1
        # this process's first device (mjx's default, jax.devices()[0], belongs to process 0 under jax.distributed)
        self.sys = mjx.put_model(sim, device=jax.local_devices()[0])
        self._implicit = sim.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST

    # ---- Brax Env interface -------------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return (4 if self.ik_observation else 3) * self.n + 6

    @property
    def action_size(self) -> int:
        return self.n

    @property
    def backend(self) -> str:
        return "mjx"

    def _f32(self, x):
        return jnp.asarray(x, jnp.float32)

    def reset(self, rng: jax.Array) -> State:
        """Random start (at rest) and target.

        ``start="random"`` (default): positions uniform in the range shrunk by ``reset_margin``;
        ``start="home"``: the ``home`` keyframe scaled joint-wise by ``U(home_scale)``, clipped to it.
        ``target="reachable"`` (default): the end-effector position of a random configuration drawn
        uniform in the shrunk range, so every target can be reached inside the joint limits;
        ``target="box"``: uniform in ``[target_low, target_high]`` (reachable only if the box is).
        """
        k_q, k_t = jax.random.split(rng)
        lim = self.limits
        span = lim.q_max - lim.q_min
        lo, hi = self._f32(lim.q_min + self.reset_margin * span), self._f32(lim.q_max - self.reset_margin * span)
        if self.start_mode == "home":
            scale = jax.random.uniform(k_q, (self.n,), jnp.float32, *self.home_scale)
            q = jnp.clip(self._f32(self.home_qpos) * scale, lo, hi)
        else:
            q = jax.random.uniform(k_q, (self.n,), jnp.float32, lo, hi)
        if self.target_mode == "reachable":
            q_t = jax.random.uniform(k_t, (self.n,), jnp.float32, lo, hi)
            target = self.ee_position(q_t)
        else:
            target = jax.random.uniform(k_t, (3,), jnp.float32, self.target_low, self.target_high)
        return self.reset_to(q, jnp.zeros_like(q), target)

    @_mjx_tracing
    def ee_position(self, q) -> jax.Array:
        """End-effector position [m] at joint positions ``q`` (MJX forward kinematics); ``(3,)``."""
        d = mjx_stages.kinematics(self.sys, mjx.make_data(self.sys).replace(qpos=self._f32(q)))
        return d.site_xpos[self.ee_site]

    @_mjx_tracing
    def ee_jacobian(self, q) -> jax.Array:
        """Jacobian of the end-effector site position at joint positions ``q``, ``(3, n)`` [m/rad]: MJX's
        analytic ``jac`` from one kinematics pass (equal to autodiff of ``ee_position``, tested; a
        forward-mode ``jacfwd`` of the kinematics traced and compiled n tangent passes per call)."""
        d = mjx_stages.kinematics(self.sys, mjx.make_data(self.sys).replace(qpos=self._f32(q)))
        return self.ee_jacobian_at(mjx_stages.com_pos(self.sys, d))

    def ee_jacobian_at(self, d) -> jax.Array:
        """The end-effector Jacobian ``(3, n)`` at ``d``'s positions, which must have their position stage
        computed (``mjx.fwd_position``, as every state's ``pipeline_state`` has): no kinematics recomputed."""
        jacp, _ = mjx.jac(self.sys, d, d.site_xpos[self.ee_site], self._ee_body)
        return jacp.T

    @_mjx_tracing
    def reset_to(self, q, v, target) -> State:
        """A state at joint positions ``q``, velocities ``v`` and end-effector target ``target``."""
        d = mjx.make_data(self.sys)
        d = d.replace(qpos=self._f32(q), qvel=self._f32(v))
        d = mjx_stages.fwd_position(self.sys, d)
        zero = jnp.zeros((), jnp.float32)
        metrics = {f"violation/{k}": zero for k in VIOLATION_KEYS}
        metrics.update({f"count/{k}": zero for k in VIOLATION_KEYS})
        metrics.update({"distance": zero, "accel_error": zero, "model_error": zero})
        info = {"target": self._f32(target), "a_prev": jnp.zeros((self.n,), jnp.float32)}
        obs = self._obs(d, info["target"])
        return State(d, obs, zero, zero, metrics, info)

    def step(self, state: State, action: jax.Array) -> State:
        """One control step with ``action * a_max`` commanded (no clipping: see ``SafetyWrapper``).

        Raises ``TypeError`` when a ``SafetyWrapper`` shields this env but its System was swapped: Brax's
        ``DomainRandomizationVmapWrapper`` (the trainers' ``randomization_fn``) steps the innermost env directly
        with each member's System, past the wrapper, which would train unshielded."""
        shielded_with = vars(self).get("_safety_sys")
        if shielded_with is not None and self.sys is not shielded_with:
            raise TypeError(
                "this env is shielded by a SafetyWrapper but was stepped directly with another System (Brax's "
                "DomainRandomizationVmapWrapper steps the innermost env past its wrappers, so it would run "
                "unshielded); for a randomised robot use JointLimitShield (e.g. over envs.reach.Reach), which acts "
                "at the innermost env"
            )
        return self.step_acc(state, action * self._f32(self.limits.a_max))

    # ---- physics --------------------------------------------------------------------------------
    def inverse_dynamics(self, d, sys=None):
        """``(M, h, d)`` at the state of ``d`` (positions/velocities), ``h = qfrc_bias - qfrc_passive``; ``d``
        with its position and velocity stages computed under ``sys`` (default ``self.sys``)."""
        sys = self.sys if sys is None else sys
        d = mjx_stages.fwd_velocity(sys, mjx_stages.fwd_position(sys, d))
        return mjx_stages.full_m(sys, d), d.qfrc_bias - d.qfrc_passive, d

    @functools.cached_property
    def _sys_without_contacts(self):
        """``sys`` with contacts disabled, for ``M`` and ``h`` alone: neither depends on contacts, and their
        collision detection is most of a position stage's program (an env with a wall traced and compiled it
        again in every shield's torque and impact model)."""
        flags = int(self.sys.opt.disableflags) | int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        return self.sys.tree_replace({"opt.disableflags": flags})

    def _substep(self, d, a):
        M, h, d = self.inverse_dynamics(d)
        tau = M @ a + h
        d = d.replace(ctrl=tau)  # clamped to ctrlrange by fwd_actuation: saturation is realised, and measured
        d = mjx_stages.fwd_acceleration(self.sys, mjx_stages.fwd_actuation(self.sys, d))
        d = d.replace(qacc=d.qacc_smooth)  # no constraints: limits and contacts are disabled
        d = mjx_stages.implicit(self.sys, d) if self._implicit else mjx_stages.euler(self.sys, d)
        return d, (d.qpos, d.qvel, d.qacc, tau)

    @_mjx_tracing
    def step_acc(self, state: State, a: jax.Array, band=None, cap_unmet=False, capped=False) -> State:
        """One control step of ``frame_skip`` substeps with joint acceleration ``a`` [rad/s^2] held.

        ``band``: the shield's bounds, ``cap_unmet``: its impact cap could not be met, and ``capped``: it has one, for
        envs with contacts (``WallStrike``); unused here (no contacts: ``a`` is realised exactly)."""
        del band, cap_unmet, capped
        a = self._f32(a)
        d0 = state.pipeline_state
        d, (qs, vs, accs, taus) = jax.lax.scan(lambda dd, _: self._substep(dd, a), d0, None, length=self.frame_skip)
        d = mjx_stages.fwd_position(self.sys, d)  # site positions at the new state, for the observation
        metrics = self._limit_metrics(state, d, a, qs, vs, accs, taus)
        target = state.info["target"]
        dist = jnp.linalg.norm(d.site_xpos[self.ee_site] - target)
        metrics["distance"] = dist
        zero = jnp.zeros((), jnp.float32)
        info = dict(state.info)
        info["a_prev"] = a
        reward = reach_reward(dist, self.precision_reward)
        return state.replace(
            pipeline_state=d, obs=self._obs(d, target), reward=reward, done=zero, metrics=metrics, info=info
        )

    def _limit_metrics(self, state: State, d, a, qs, vs, accs, taus) -> dict:
        """``state.metrics`` updated with one step's ``violation/*``, ``count/*``, ``accel_error`` and
        ``model_error``, from the substeps' positions ``qs``, velocities ``vs``, accelerations ``accs``
        and torques ``taus`` (each ``(frame_skip, n)``), the command ``a`` and the end state ``d``."""
        lim = self.limits
        f = self._f32
        zero = jnp.zeros((), jnp.float32)

        def excess(x):
            return jnp.maximum(jnp.max(x), zero)

        viol = {
            "position": excess(jnp.maximum(qs - f(lim.q_max)[None], f(lim.q_min)[None] - qs)),
            "velocity": excess(jnp.abs(vs) - f(lim.v_max)[None]),
            "acceleration": excess(jnp.abs(a) - f(lim.a_max)),
            "jerk": excess(jnp.abs(a - state.info["a_prev"]) - f(lim.j_max) * self.dt)
            if lim.j_max is not None
            else zero,
            "torque": excess(jnp.abs(taus) - f(self.tau_max)[None]),
            "impact": zero,  # no contacts here (WallStrike measures its strikes)
        }
        d0 = state.pipeline_state
        model = jl.integrate_step(d0.qpos, d0.qvel, a, self.dt, "semi_implicit", self.frame_skip)
        metrics = dict(state.metrics)
        for k, x in viol.items():
            metrics[f"violation/{k}"] = x
            metrics[f"count/{k}"] = (x > 0).astype(jnp.float32)
        metrics["accel_error"] = jnp.max(jnp.abs(accs - a[None]))
        metrics["model_error"] = jnp.maximum(jnp.max(jnp.abs(d.qpos - model.q)), jnp.max(jnp.abs(d.qvel - model.v)))
        return metrics

    def _obs(self, d, target):
        ee = d.site_xpos[self.ee_site]
        parts = [jnp.cos(d.qpos), jnp.sin(d.qpos), d.qvel, ee, target - ee]
        if self.ik_observation:
            parts.append(self.ik_step(d, target - ee))
        return jnp.concatenate(parts).astype(jnp.float32)

    def ik_step(self, d, err):
        """Damped least-squares joint step ``J^T (J J^T + lam^2 I)^-1 err`` [rad], ``(n,)``, at ``d``'s positions.

        ``d`` must have its position stage computed (``mjx.fwd_position``); ``err`` ``(3,)`` [m].
        ``lam = IK_DAMPING`` keeps it finite and bounded (``<= |err| / (2 lam)``) at singularities.
        """
        return damped_ls_step(self.ee_jacobian_at(d), err)

    # ---- MJX-backed dynamics for jaxlimits.torque ----------------------------------------------
    @_mjx_tracing
    def mass_and_bias(self, q, v):
        """``(M(q), h(q, v))`` from MJX for one state, ``h = qfrc_bias - qfrc_passive``; vmappable."""
        sys = self._sys_without_contacts
        d = mjx.make_data(sys).replace(qpos=self._f32(q), qvel=self._f32(v))
        M, h, _ = self.inverse_dynamics(d, sys)
        return M, h


def make_planar_reach(**kwargs) -> ArmReach:
    """Planar 3-link arm (``assets/planar3.xml``), Euler, 5 substeps of 2 ms: dt = 10 ms."""
    return ArmReach(ASSETS / "planar3.xml", "ee", (-0.7, 0.0, -0.7), (0.7, 0.0, 0.7), **kwargs)


def make_panda_reach(**kwargs) -> ArmReach:
    """Mesh-free Franka Panda (``assets/panda.xml``), implicitfast, 5 substeps of 2 ms: dt = 10 ms."""
    return ArmReach(ASSETS / "panda.xml", "ee", (0.2, -0.5, 0.1), (0.7, 0.5, 0.8), **kwargs)


PANDA_FRONT_BOX = ((0.35, -0.2, 0.15), (0.65, 0.2, 0.5))  # Isaac Lab Reach-Franka's target ranges [m]


def make_panda_front_reach(**kwargs) -> ArmReach:
    """The Panda reach of Isaac Lab's ``Isaac-Reach-Franka-v0``: start at the ``home`` keyframe with every
    joint scaled by ``U(0.5, 1.5)``; target uniform in the box ``PANDA_FRONT_BOX`` in front of the robot
    (x 0.35–0.65, y −0.2–0.2, z 0.15–0.5 m, base frame; here for the flange site, no orientation).
    ``make_panda_reach``'s task (start and target anywhere in the joint ranges) is the harder one."""
    kwargs = {"start": "home", "target": "box", **kwargs}
    return ArmReach(ASSETS / "panda.xml", "ee", *PANDA_FRONT_BOX, **kwargs)
