"""A reach *task* over any robot MJCF (Brax ``PipelineEnv``, MJX backend): move the site ``ee`` to a target.

    env = Reach("envs/assets/panda_servo.xml")          # the shipped position-servo Panda
    env = JointLimitShield(env)                          # v_max/j_max from its custom numerics

The task knows nothing of the limits: the action ``[-1, 1]^nu`` is mapped affinely onto each
actuator's ``ctrlrange`` (for a position servo, a target joint position inside the joint range, as
in MuJoCo Playground; for a motor, a torque) and held over ``n_frames`` substeps by
``pipeline_step``, where a ``JointLimitShield`` takes over. Reward ``-|ee - target|`` [m]; targets are
end-effector positions of random configurations inside the limits (reachable); episodes do not
terminate (truncate them with Brax's ``EpisodeWrapper``).
"""

from __future__ import annotations

import pathlib
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from brax.envs.base import PipelineEnv, State
    from brax.io import mjcf

ASSETS = pathlib.Path(__file__).parent / "assets"


class Reach(PipelineEnv):
    """Reach over the robot in ``xml_path`` (every actuator needs a ``ctrlrange``; a site named ``ee_site``).

    Args:
      xml_path: the robot's MJCF. n_frames: physics substeps per control step.
      reset_margin: initial and target configurations are uniform in each limited joint's range shrunk
        by this fraction at both ends (unlimited joints: in [-pi, pi]).
    """

    def __init__(self, xml_path, ee_site: str = "ee", n_frames: int = 5, reset_margin: float = 0.1):
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
        span = mjm.jnt_range[:, 1] - mjm.jnt_range[:, 0]
        q_lo = np.where(lim, mjm.jnt_range[:, 0] + reset_margin * span, -np.pi)
        q_hi = np.where(lim, mjm.jnt_range[:, 1] - reset_margin * span, np.pi)
        hinge = np.isin(mjm.jnt_type, [int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)])
        if mjm.nq != mjm.njnt or not np.all(hinge):
            raise ValueError(f"{xml_path}: Reach expects a fixed-base arm of hinge/slide joints only")
        self._q_lo, self._q_hi = jnp.asarray(q_lo, jnp.float32), jnp.asarray(q_hi, jnp.float32)

    def _ee(self, q):
        with jax.numpy_rank_promotion("allow"):
            d = mjx.kinematics(self.sys, mjx.make_data(self.sys).replace(qpos=q))
        return d.site_xpos[self._site]

    def reset(self, rng: jax.Array) -> State:
        k_q, k_t = jax.random.split(rng)
        q = jax.random.uniform(k_q, self._q_lo.shape, jnp.float32, self._q_lo, self._q_hi)
        target = self._ee(jax.random.uniform(k_t, self._q_lo.shape, jnp.float32, self._q_lo, self._q_hi))
        with jax.numpy_rank_promotion("allow"):
            ps = self.pipeline_init(q, jnp.zeros(self.sys.nv, jnp.float32))
        zero = jnp.zeros((), jnp.float32)
        dist = jnp.linalg.norm(ps.site_xpos[self._site] - target)
        return State(ps, self._obs(ps, target), -dist, zero, {"distance": dist}, {"target": target})

    def step(self, state: State, action: jax.Array) -> State:
        ctrl = self._ctrl_mid + action * self._ctrl_half
        ps = self.pipeline_step(state.pipeline_state, ctrl)
        target = state.info["target"]
        dist = jnp.linalg.norm(ps.site_xpos[self._site] - target)
        metrics = dict(state.metrics, distance=dist)
        return state.replace(pipeline_state=ps, obs=self._obs(ps, target), reward=-dist, metrics=metrics)

    def _obs(self, ps, target):
        ee = ps.site_xpos[self._site]
        return jnp.concatenate([jnp.cos(ps.qpos), jnp.sin(ps.qpos), ps.qvel, ee, target - ee]).astype(jnp.float32)


def make_servo_panda_reach(**kwargs) -> Reach:
    """Reach with the shipped position-servo Panda (``assets/panda_servo.xml``), 5 substeps of 2 ms."""
    return Reach(ASSETS / "panda_servo.xml", **kwargs)


def make_ur5e_reach(**kwargs) -> Reach:
    """Reach with the shipped UR5e (``assets/ur5e.xml``, Menagerie's servos), 5 substeps of 2 ms."""
    return Reach(ASSETS / "ur5e.xml", **kwargs)
