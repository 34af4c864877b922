"""A reach *task* over any robot MJCF (Brax ``PipelineEnv``, MJX backend): move the site ``ee`` to a target.

    env = Reach("envs/assets/panda_servo.xml")          # the shipped position-servo Panda
    env = JointLimitShield(env)                          # v_max/j_max from its custom numerics

The task knows nothing of the limits. The action ``[-1, 1]^nu`` means (``action``):

* ``"ctrl"`` (default): mapped affinely onto each actuator's ``ctrlrange`` (for a position servo, a
  target joint position inside the joint range, as in MuJoCo Playground; for a motor, a torque);
* ``"servo_offset"`` (position servos only): the servo's target is the joint's current position plus
  ``action * forcerange / kp`` [rad or m], so ``|action| = 1`` asks the servo's whole force at rest and
  the policy commands a direction of motion, not a place (``servo_offset_scale``);
* ``"acceleration"``: a joint acceleration ``action * acceleration_scale`` [rad/s^2], ``ArmReach``'s action space on
  any robot whose every joint has its own actuator: the ``ctrl`` that asks the integrator for it at the step's start
  state (``acceleration_actions.AccelerationActions``; the scale defaults to the MJCF's ``jaxlimits_a_max``).

Either way ``ctrl`` is held over ``n_frames`` substeps by ``pipeline_step``, where a
``JointLimitShield`` takes over. Reward ``-d`` (``d = |ee - target|`` [m]), plus
``precision_reward * (1 - tanh(d / PRECISION_SCALE))`` if asked (``jaxlimits.envs.arm.reach_reward``,
the same as ``ArmReach``'s). Starts: uniform in the joint ranges or Isaac Lab's ``home`` scaling;
targets: end-effector positions of random configurations inside the limits (reachable) or uniform in a
box. Episodes do not terminate (truncate them with Brax's ``EpisodeWrapper``).
"""

from __future__ import annotations

import pathlib
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxlimits.envs import mjx_stages
from jaxlimits.envs.acceleration_actions import AccelerationActions

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from brax.envs.base import PipelineEnv, State
    from brax.io import mjcf

from jaxlimits.envs.arm import PANDA_FRONT_BOX, _mjx_tracing, damped_ls_step, reach_reward

ASSETS = pathlib.Path(__file__).parent / "assets"
ACTIONS = ("ctrl", "servo_offset", "acceleration")
STARTS = ("random", "home")
TARGETS = ("reachable", "box")


def servo_offset_scale(mjm: mujoco.MjModel) -> np.ndarray:
    """``(nu,)`` [rad or m]: ``forcerange_hi / kp`` of every actuator, each a position servo on a joint with
    gear 1 (``<position>``, or ``general`` with gain ``kp`` and bias ``(0, -kp, -kv)``) and a force range.

    Raises ``ValueError`` naming the first actuator that is not one."""
    out = np.empty(mjm.nu)
    for i in range(mjm.nu):
        name = mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}"
        kp = float(mjm.actuator_gainprm[i, 0])
        servo = (
            mjm.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
            and mjm.actuator_gear[i, 0] == 1  # the servo's target is then the joint's position itself
            and mjm.actuator_gaintype[i] == mujoco.mjtGain.mjGAIN_FIXED
            and mjm.actuator_biastype[i] == mujoco.mjtBias.mjBIAS_AFFINE
            and kp > 0
            and mjm.actuator_biasprm[i, 0] == 0
            and mjm.actuator_biasprm[i, 1] == -kp
        )
        if not servo:
            raise ValueError(f"action='servo_offset' needs position servos; actuator {name!r} is not one")
        if not mjm.actuator_forcelimited[i]:
            raise ValueError(f"action='servo_offset' needs a forcerange; actuator {name!r} has none")
        out[i] = float(mjm.actuator_forcerange[i, 1]) / kp
    return out


class Reach(PipelineEnv):
    """Reach over the robot in ``xml_path`` (every actuator needs a ``ctrlrange``; a site named ``ee_site``).

    Args:
      xml_path: the robot's MJCF (a fixed-base arm of hinge/slide joints). n_frames: physics substeps
        per control step.
      reset_margin: random configurations (starts, reachable targets) are uniform in each limited
        joint's range shrunk by this fraction at both ends (unlimited joints: in [-pi, pi]).
      action: ``"ctrl"``, ``"servo_offset"`` or ``"acceleration"`` (module docstring).
      acceleration_scale: [rad/s^2 or m/s^2] per unit action for ``action="acceleration"``, scalar or per actuator
        (default: the MJCF custom numeric ``jaxlimits_a_max``).
      start: ``"random"`` (uniform, as above) or ``"home"`` (the keyframe ``home`` with every joint scaled
        by ``U(home_scale)``, clipped to the shrunk ranges: Isaac Lab's ``reset_joints_by_scale``).
      target: ``"reachable"`` (the ``ee`` position of a random configuration) or ``"box"`` (uniform in
        ``target_box = (low, high)`` [m], world frame).
      ik_observation: append the damped least-squares joint step toward the target (``n`` entries,
        ``arm.damped_ls_step``), as ``ArmReach`` does.
      precision_reward: weight of the precision term of the reward (``arm.reach_reward``), >= 0.
    """

    def __init__(
        self,
        xml_path,
        ee_site: str = "ee",
        n_frames: int = 5,
        reset_margin: float = 0.1,
        action: str = "ctrl",
        start: str = "random",
        home_scale=(0.5, 1.5),
        target: str = "reachable",
        target_box=None,
        ik_observation: bool = False,
        precision_reward: float = 0.0,
        acceleration_scale=None,
    ):
        for field, value, allowed in (
            ("action", action, ACTIONS),
            ("start", start, STARTS),
            ("target", target, TARGETS),
        ):
            if value not in allowed:
                raise ValueError(f"{field} must be one of {allowed}, got {value!r}")
        if not (np.isfinite(precision_reward) and precision_reward >= 0):
            raise ValueError(f"precision_reward must be a finite number >= 0, got {precision_reward!r}")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            sys = mjcf.load_model(mujoco.MjModel.from_xml_path(str(xml_path)))
        mjm = sys.mj_model
        if not np.all(mjm.actuator_ctrllimited):
            raise ValueError(f"{xml_path}: every actuator needs a ctrlrange (the action is mapped onto it)")
        self._site = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_SITE, ee_site)
        if self._site < 0:
            raise ValueError(f"{xml_path}: no site named {ee_site!r}")
        super().__init__(sys=sys, backend="mjx", n_frames=n_frames)
        lo, hi = mjm.actuator_ctrlrange[:, 0], mjm.actuator_ctrlrange[:, 1]
        self._ctrl_mid = jnp.asarray((lo + hi) / 2, jnp.float32)
        self._ctrl_half = jnp.asarray((hi - lo) / 2, jnp.float32)
        lim = mjm.jnt_limited.astype(bool)
        rng = np.where(lim[:, None], mjm.jnt_range, 0.0)  # Brax writes an unlimited joint's range as +-inf
        span = rng[:, 1] - rng[:, 0]
        q_lo = np.where(lim, rng[:, 0] + reset_margin * span, -np.pi)
        q_hi = np.where(lim, rng[:, 1] - reset_margin * span, np.pi)
        hinge = np.isin(mjm.jnt_type, [int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)])
        if mjm.nq != mjm.njnt or not np.all(hinge):
            raise ValueError(f"{xml_path}: Reach expects a fixed-base arm of hinge/slide joints only")
        self._q_lo, self._q_hi = jnp.asarray(q_lo, jnp.float32), jnp.asarray(q_hi, jnp.float32)
        self.action_mode = action
        if action == "servo_offset":
            self._offset_scale = jnp.asarray(servo_offset_scale(mjm), jnp.float32)
            self._servo_qadr = jnp.asarray(mjm.jnt_qposadr[mjm.actuator_trnid[:, 0]])
        if action == "acceleration":
            self._accelerations = AccelerationActions(sys, acceleration_scale)
        elif acceleration_scale is not None:
            raise ValueError(f"acceleration_scale is for action='acceleration', not {action!r}")
        self.start_mode, self.target_mode = start, target
        if start == "home":
            key = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_KEY, "home")
            if key < 0:
                raise ValueError(f"{xml_path}: start='home' needs a keyframe named 'home'")
            self._home = jnp.asarray(mjm.key_qpos[key], jnp.float32)
            lo_s, hi_s = (float(x) for x in home_scale)
            if not (np.isfinite(lo_s) and np.isfinite(hi_s) and lo_s <= hi_s):
                raise ValueError(f"home_scale must be finite (low, high) with low <= high, got {home_scale!r}")
            self._home_scale = (lo_s, hi_s)
        if target == "box":
            box = np.asarray(target_box, np.float64) if target_box is not None else None
            if box is None or box.shape != (2, 3) or not np.all(np.isfinite(box)) or np.any(box[0] > box[1]):
                raise ValueError(
                    f"target='box' needs target_box = (low, high), two finite 3-vectors, got {target_box!r}"
                )
            self._box = jnp.asarray(box, jnp.float32)
        self.ik_observation = bool(ik_observation)
        self.precision_reward = float(precision_reward)
        self._body = int(mjm.site_bodyid[self._site])

    @property
    def mj_model(self) -> mujoco.MjModel:
        """The robot's ``MjModel`` (for reading and rendering)."""
        return self.sys.mj_model

    @_mjx_tracing
    def _ee(self, q):
        d = mjx_stages.kinematics(self.sys, mjx.make_data(self.sys).replace(qpos=q))
        return d.site_xpos[self._site]

    @_mjx_tracing
    def reset(self, rng: jax.Array) -> State:
        k_q, k_t = jax.random.split(rng)
        if self.start_mode == "home":
            scale = jax.random.uniform(k_q, self._q_lo.shape, jnp.float32, *self._home_scale)
            q = jnp.clip(self._home * scale, self._q_lo, self._q_hi)
        else:
            q = jax.random.uniform(k_q, self._q_lo.shape, jnp.float32, self._q_lo, self._q_hi)
        if self.target_mode == "box":
            target = jax.random.uniform(k_t, (3,), jnp.float32, self._box[0], self._box[1])
        else:
            target = self._ee(jax.random.uniform(k_t, self._q_lo.shape, jnp.float32, self._q_lo, self._q_hi))
        ft = jnp.result_type(float)  # the physics' dtype: float64 under jax_enable_x64 (MJX computes in it)
        ps = self.pipeline_init(q.astype(ft), jnp.zeros(self.sys.nv, ft))
        zero = jnp.zeros((), jnp.float32)
        dist = jnp.linalg.norm(ps.site_xpos[self._site] - target)
        return State(ps, self._obs(ps, target), -dist, zero, {"distance": dist}, {"target": target})

    @_mjx_tracing
    def ctrl(self, pipeline_state, action: jax.Array) -> jax.Array:
        """The actuators' ``ctrl`` ``(nu,)`` for ``action`` ``(nu,)`` at ``pipeline_state`` (module docstring)."""
        if self.action_mode == "servo_offset":
            ctrl = pipeline_state.qpos[self._servo_qadr] + action * self._offset_scale
        elif self.action_mode == "acceleration":
            ctrl = self._accelerations.ctrl(self.sys, pipeline_state, action)
        else:
            ctrl = self._ctrl_mid + action * self._ctrl_half
        return ctrl.astype(pipeline_state.qpos.dtype)  # the physics' dtype (float64 under jax_enable_x64)

    @_mjx_tracing
    def step(self, state: State, action: jax.Array) -> State:
        ps = self.pipeline_step(state.pipeline_state, self.ctrl(state.pipeline_state, action))
        target = state.info["target"]
        dist = jnp.linalg.norm(ps.site_xpos[self._site] - target)
        metrics = dict(state.metrics, distance=dist)
        reward = reach_reward(dist, self.precision_reward)
        return state.replace(pipeline_state=ps, obs=self._obs(ps, target), reward=reward, metrics=metrics)

    def _obs(self, ps, target):
        ee = ps.site_xpos[self._site]
        parts = [jnp.cos(ps.qpos), jnp.sin(ps.qpos), ps.qvel, ee, target - ee]
        if self.ik_observation:
            jacp, _ = mjx.jac(self.sys, ps, ee, self._body)  # under reset's / step's _mjx_tracing
            parts.append(damped_ls_step(jacp.T, target - ee))
        return jnp.concatenate(parts).astype(jnp.float32)


def make_servo_panda_reach(**kwargs) -> Reach:
    """Reach with the shipped position-servo Panda (``assets/panda_servo.xml``), 5 substeps of 2 ms."""
    return Reach(ASSETS / "panda_servo.xml", **kwargs)


def make_planar_robot_reach(**kwargs) -> Reach:
    """The project's planar 3-link arm (``assets/planar3.xml``, motors, Euler) as a robot under the one shield:
    ``ArmReach``'s planar reach (5 substeps of 2 ms, reachable targets) with joint-acceleration actions scaled by
    its ``jaxlimits_a_max`` (``action="acceleration"`` by default)."""
    return Reach(ASSETS / "planar3.xml", **{"action": "acceleration", **kwargs})


def make_servo_panda_front_reach(**kwargs) -> Reach:
    """Isaac Lab's ``Isaac-Reach-Franka-v0`` distribution (as ``arm.make_panda_front_reach``) on the
    position-servo Panda: start at ``home`` scaled by ``U(0.5, 1.5)``, target uniform in
    ``arm.PANDA_FRONT_BOX``; servo-offset actions and the IK observation by default."""
    kwargs = {
        "start": "home",
        "target": "box",
        "target_box": PANDA_FRONT_BOX,
        "action": "servo_offset",
        "ik_observation": True,
        **kwargs,
    }
    return Reach(ASSETS / "panda_servo.xml", **kwargs)


def make_ur5e_reach(**kwargs) -> Reach:
    """Reach with the shipped UR5e (``assets/ur5e.xml``, Menagerie's servos), 5 substeps of 2 ms."""
    return Reach(ASSETS / "ur5e.xml", **kwargs)


def make_gen3_reach(**kwargs) -> Reach:
    """Reach with the shipped Kinova Gen3 (``assets/gen3.xml``, Menagerie's servos, four unlimited joints), 5
    substeps of 2 ms."""
    return Reach(ASSETS / "gen3.xml", **kwargs)
