"""Robot.from_model over MJCF strings: joint selection, limits, supported actuators, eager errors."""

import jaxlimits.envs  # noqa: F401

import mujoco
import numpy as np
import pytest

from jaxlimits.envs.actuation import CActuation
from jaxlimits.envs.robot import Robot

ARM = """
<mujoco><option timestep="0.002" integrator="{integrator}"/>
  <worldbody>
    <body name="obj" pos="1 0 0"><freejoint/><geom size="0.05" mass="0.1"/></body>
    <body name="l1"><joint name="j1" axis="0 1 0" range="-1 1" damping="{damping}" armature="0.01"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="l2" pos="0.3 0 0"><joint name="j2" axis="0 1 0" {j2}/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
        <body pos="0.3 0 0"><joint name="s3" type="slide" axis="1 0 0" range="-0.1 0.1"/>
          <geom size="0.02" mass="0.2"/></body>
      </body>
    </body>
  </worldbody>
  <actuator>{actuators}</actuator>
</mujoco>"""
MOTORS = (
    '<motor joint="j1" gear="50" ctrlrange="-1 1"/><position joint="j2" kp="200" kv="4" ctrlrange="-4 4" '
    'forcerange="-50 50"/><motor joint="s3" ctrlrange="-30 30"/>'
)


def _model(integrator="implicitfast", damping=0.5, j2="", actuators=MOTORS):
    return mujoco.MjModel.from_xml_string(
        ARM.format(integrator=integrator, damping=damping, j2=j2, actuators=actuators)
    )


def test_default_joints_are_the_driven_hinges_and_slides_and_free_joints_are_skipped():
    r = Robot.from_model(_model(), v_max=2.0)
    assert r.names == ("j1", "j2", "s3")
    assert list(r.limited) == [True, False, True]  # j2 has no range: no position limit
    np.testing.assert_allclose(r.gear, [50, 1, 1])
    np.testing.assert_allclose(r.tau_max > 0, True)
    assert r.a_max_source == "torque" and np.all(r.limits.a_max > 0)
    assert r.qpos_adr.tolist() == [7, 8, 9] and r.dof_adr.tolist() == [6, 7, 8]


@pytest.mark.parametrize("integrator", ["Euler", "implicitfast", "RK4"])
def test_actuation_realises_the_acceleration_through_motors_and_servos(integrator):
    m = _model(integrator)
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    r = Robot.from_model(m, v_max=2.0)
    act, d = CActuation(r, m), mujoco.MjData(m)
    rng = np.random.default_rng(0)
    worst = 0.0
    for _ in range(100):
        a = rng.uniform(-0.3, 0.3, r.n) * r.limits.a_max
        v0 = d.qvel[r.dof_adr].copy()
        _, M, f = act.smooth_stage(d, np.zeros(m.nu))
        inv, _ = act.finish_substep(d, M, f, a)
        assert not inv.saturated.any()
        worst = max(worst, np.max(np.abs((d.qvel[r.dof_adr] - v0) / m.opt.timestep - a)))
        d.qvel[r.dof_adr] *= 0.5
    # Euler/implicitfast: exact; RK4 holds ctrl over its stages: first order compensated, the rest
    # grows with the servo's (omega h)^2 (here kp 200 on a 0.5 kg link: ~2 % of a_max)
    assert worst < (1e-9 if integrator != "RK4" else 3e-2 * np.max(r.limits.a_max)), worst


def test_unknown_joint_lists_the_valid_ones():
    with pytest.raises(ValueError, match=r"unknown joint 'elbow'.*\['j1', 'j2', 's3'\]"):
        Robot.from_model(_model(), joints=["elbow"], v_max=1.0)


def test_missing_velocity_limit_names_the_joints():
    with pytest.raises(ValueError, match="no velocity limit for joints"):
        Robot.from_model(_model())


def test_unsupported_actuator_is_named():
    acts = MOTORS.replace(
        '<motor joint="j1" gear="50" ctrlrange="-1 1"/>',
        '<general name="filt" joint="j1" dyntype="filter" ctrlrange="-1 1"/>',
    )
    with pytest.raises(ValueError, match="actuator 'filt' cannot be inverted.*dyntype"):
        Robot.from_model(_model(actuators=acts), v_max=1.0)


def test_joint_without_actuator_is_an_error_when_asked_for():
    acts = MOTORS.replace('<motor joint="s3" ctrlrange="-30 30"/>', "")
    r = Robot.from_model(_model(actuators=acts), v_max=1.0)
    assert r.names == ("j1", "j2")
    with pytest.raises(ValueError, match="joint 's3' is driven by no actuator"):
        Robot.from_model(_model(actuators=acts), joints=["j1", "s3"], v_max=1.0)


def test_bad_limit_values_name_the_field():
    with pytest.raises(ValueError, match="v_max must be finite and > 0"):
        Robot.from_model(_model(), v_max=[1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="one value per shielded joint"):
        Robot.from_model(_model(), v_max=[1.0, 1.0])


def test_from_model_is_cached_on_the_models_content_and_the_arguments():
    """``N`` copies of one env read their robot once: the same model content and arguments give the same object,
    a model changed in place or other arguments are read again, and the reading's warnings are given every time."""
    import warnings

    import gymnasium

    pusher = gymnasium.make("Pusher-v5").unwrapped.model  # its torque-derived a_max warns (a quantile)
    again = gymnasium.make("Pusher-v5").unwrapped.model
    for model in (pusher, again):
        with pytest.warns(UserWarning, match="quantile"):
            robot = Robot.from_model(model, v_max=[2.0] * 7)
        if model is pusher:
            first = robot
    assert robot is first  # a separate MjModel with the same content, v_max as a list
    with pytest.warns(UserWarning, match="quantile"):
        assert Robot.from_model(pusher, v_max=np.full(7, 2.0)) is first  # the same numbers as an array
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        slower = Robot.from_model(pusher, v_max=1.0)
        assert slower is not first and np.all(slower.limits.v_max == 1.0)
        pusher.actuator_gear[0, 0] *= 2.0  # changed in place: read again
        stronger = Robot.from_model(pusher, v_max=[2.0] * 7)
    assert stronger is not first and stronger.gear[0] == 2.0 * first.gear[0]
    assert not np.array_equal(stronger.limits.a_max, first.limits.a_max)  # derived from the changed model
