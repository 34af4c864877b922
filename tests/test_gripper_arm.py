"""An arm with a gripper as Menagerie's Panda has one (a tendon-driven actuator, two finger slide joints coupled by
an equality, on the arm's own kinematic tree; ranges of 2 degrees on the arm): the default shielded joints are the
arm's, and under adversarial arm commands with the gripper slammed open and shut the shielded arm breaks no limit
(C MuJoCo, Gymnasium); the unshielded arm does. The fingers pressed against their own limits push the arm through
``M``: with one correction pass per substep the arm broke its limits in 64 of these 1 800 steps (by up to
1.7e-5 rad); a coupled robot now gets ``MJX_CORRECTION_PASSES`` in C MuJoCo too, as on MJX."""

import warnings

import numpy as np
import pytest

from jaxlimits.envs.gym import JointLimitShieldWrapper
from small_mujoco_env import SmallMujocoEnv

XML = """
<mujoco>
  <option timestep="0.002" integrator="implicitfast"/>
  <default><joint damping="1" armature="0.1"/></default>
  <worldbody>
    <body name="l1"><joint name="j1" axis="0 0 1" range="-2 2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="2"/>
      <body name="l2" pos="0.3 0 0"><joint name="j2" axis="0 0 1" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
        <body name="hand" pos="0.3 0 0"><geom type="box" size="0.02 0.05 0.02" mass="0.5"/>
          <body name="lf" pos="0.03 0 0"><joint name="f1" type="slide" axis="0 1 0" range="0 0.04"/>
            <geom type="box" size="0.01 0.005 0.02" mass="0.3"/></body>
          <body name="rf" pos="0.03 0 0"><joint name="f2" type="slide" axis="0 -1 0" range="0 0.04"/>
            <geom type="box" size="0.01 0.005 0.02" mass="0.3"/></body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon><fixed name="split"><joint joint="f1" coef="0.5"/><joint joint="f2" coef="0.5"/></fixed></tendon>
  <equality><joint joint1="f1" joint2="f2" solimp="0.95 0.99 0.001" solref="0.005 1"/></equality>
  <actuator>
    <position name="a1" joint="j1" kp="200" kv="20" ctrlrange="-2 2" forcerange="-40 40"/>
    <position name="a2" joint="j2" kp="100" kv="10" ctrlrange="-2 2" forcerange="-20 20"/>
    <general name="grip" tendon="split" forcerange="-100 100" ctrlrange="0 255" gainprm="0.0157 0 0"
             biasprm="0 -100 -10"/>
  </actuator>
</mujoco>"""


def GripperArm(path):
    """The smallest Gymnasium ``MujocoEnv`` over ``XML``: 5 substeps per step, no reward."""
    return SmallMujocoEnv(path)


@pytest.fixture(scope="module")
def xml_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("gripper") / "gripper_arm.xml"
    path.write_text(XML)
    return path


def _run(env, episodes=12, steps=150):
    rng = np.random.default_rng(0)
    lo, hi = env.action_space.low, env.action_space.high
    counts = {"position": 0, "velocity": 0}
    for ep in range(episodes):
        env.reset(seed=ep)
        period = int(rng.integers(3, 40))
        for t in range(steps):
            a = [hi, lo, np.where((t // period) % 2, hi, lo), rng.uniform(lo, hi)][ep % 4].copy()
            a[2] = 255.0 * ((t // 7) % 2)  # the gripper slammed open and shut
            _, _, _, _, info = env.step(a)
            for k in counts:
                counts[k] += info["violation"][k] > 0
    return counts


def test_a_gripper_on_the_arm_tree_leaves_the_arm_safe(xml_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        shielded = JointLimitShieldWrapper(GripperArm(xml_path), v_max=2.0)
        unshielded = JointLimitShieldWrapper(GripperArm(xml_path), v_max=2.0, method="none")
    assert shielded.robot.names == ("j1", "j2")  # the fingers, driven through a tendon, are not shielded
    assert shielded.robot.coupled  # they share the arm's chain: the actuation solves for them too
    assert _run(shielded) == {"position": 0, "velocity": 0}
    off = _run(unshielded)
    assert off["position"] + off["velocity"] > 100, off
