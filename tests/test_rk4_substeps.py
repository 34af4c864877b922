"""RK4 in C MuJoCo (Gymnasium's Ant, Hopper, Walker2d, Reacher, ...): ``ctrl`` is held over RK4's four stages,
so the realised acceleration of a substep is the held one only to first order, and a contact (one already
touching, or one that begins within the substep) acts differently on each stage. ``CActuation`` retakes a
substep whose realised acceleration ``(v+ - v) / h`` left the decision's band (``_rk4_step_in_band``). Each
test fails on the code before (no retake: the first stage's contact correction only, or none)."""

import jaxlimits.envs  # noqa: F401

import warnings

import gymnasium
import mujoco
import numpy as np
import pytest

from jaxlimits.envs import actuation
from jaxlimits.envs.actuation import CActuation
from jaxlimits.envs.gym import JointLimitShieldWrapper
from jaxlimits.envs.robot import Robot, _condition_11_cap

# a slide joint with a spring and a damper fast against the 10 ms substep (rate 100 /s), no contact
SPRING = """<mujoco><option timestep="0.01" gravity="0 0 0" integrator="RK4"/>
  <worldbody><body><joint name="x" type="slide" axis="1 0 0" range="-1 1" damping="10" stiffness="100"/>
    <geom size="0.05" mass="0.1" contype="0" conaffinity="0"/></body></worldbody>
  <actuator><motor joint="x" ctrlrange="-1 1" gear="100"/></actuator></mujoco>"""
# a sphere on two actuated slides pressed 5 mm into the floor (as tests/test_contact_correction.py), RK4
FLOOR = """<mujoco><option timestep="0.002" gravity="0 0 0" integrator="RK4"/>
  <worldbody><geom type="plane" size="1 1 0.1"/>
    <body pos="0 0 0.045"><joint name="x" type="slide" axis="1 0 0" range="-1 1" damping="0.5"/>
      <joint name="z" type="slide" axis="0 0 1" range="-1 1"/><geom size="0.05" mass="1"/></body></worldbody>
  <actuator><motor joint="x" ctrlrange="-1 1" gear="{gear}"/><motor joint="z" ctrlrange="-1 1" gear="{gear}"/></actuator>
</mujoco>"""


def _substep(xml, a, band, q0=None, v0=None, rk4_tol=0.0, **robot_kw):
    mjm = mujoco.MjModel.from_xml_string(xml)
    robot = Robot.from_model(mjm, **robot_kw)
    d = mujoco.MjData(mjm)
    if q0 is not None:
        d.qpos[:] = q0
    if v0 is not None:
        d.qvel[:] = v0
    act = CActuation(robot, mjm)
    _, M, f = act.smooth_stage(d, np.zeros(mjm.nu))
    v_start = d.qvel.copy()
    inv, _ = act.finish_substep(d, M, f, np.asarray(a, float), band, rk4_tol)
    return (d.qvel - v_start) / mjm.opt.timestep, inv


@pytest.mark.parametrize("v0, a", [(1.0, -1.0), (-1.0, 1.0)])
def test_a_substep_that_leaves_the_band_is_retaken_at_its_edge(v0, a):
    band = (np.array([-1.0]), np.array([1.0]))
    free, _ = _substep(SPRING, [a], None, q0=[0.3], v0=[v0], v_max=2.0, a_max=1.0)
    assert abs(free[0]) > 1.5  # held ctrl over the stages: 55 % past the band's edge
    r, inv = _substep(SPRING, [a], band, q0=[0.3], v0=[v0], v_max=2.0, a_max=1.0)
    assert abs(r[0] - a) < 1e-6, r
    assert not inv.saturated[0]


def test_a_substep_inside_the_band_is_the_plain_step():
    """Deviating inward is physics: not retaken, the same substep as without a band."""
    band = (np.array([-1.0]), np.array([1.0]))
    free, inv_free = _substep(SPRING, [1.0], None, q0=[0.3], v0=[1.0], v_max=2.0, a_max=1.0)
    r, inv = _substep(SPRING, [1.0], band, q0=[0.3], v0=[1.0], v_max=2.0, a_max=1.0)
    assert -1.0 <= free[0] < 1.0 - 1e-3
    np.testing.assert_array_equal(r, free)
    np.testing.assert_array_equal(inv.ctrl, inv_free.ctrl)


def test_the_retake_tolerance_leaves_small_deviations_to_the_margin():
    band = (np.array([-1.0]), np.array([1.0]))
    free, _ = _substep(SPRING, [-1.0], None, q0=[0.3], v0=[1.0], v_max=2.0, a_max=1.0)
    r, _ = _substep(SPRING, [-1.0], band, q0=[0.3], v0=[1.0], rk4_tol=1.0, v_max=2.0, a_max=1.0)
    np.testing.assert_array_equal(r, free)  # 0.55 over, under the tolerance of 1: kept


def test_an_rk4_contact_is_held_at_the_band():
    band = (np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
    xml = FLOOR.format(gear=400.0)
    free, _ = _substep(xml, [0.5, 0.0], None, v_max=1.0, a_max=2.0)
    assert free[1] > 5.0  # the floor's push, uncorrected (~11 m/s^2)
    r, inv = _substep(xml, [0.5, 0.0], band, v_max=1.0, a_max=2.0)
    assert not np.any(inv.saturated)
    assert band[0][1] < r[1] <= band[1][1] + 1e-6, r  # the push kept, as far as the band allows
    assert band[0][0] <= r[0] <= band[1][0], r


def test_too_weak_an_actuator_keeps_the_best_pass(monkeypatch):
    """2 N cannot hold the sphere: the retakes stop at a pass that is no better (saturated) and the best is kept:
    the first stage's correction, its torque shortfall counted (not the runaway of an unchecked iteration)."""
    band = (np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
    xml = FLOOR.format(gear=2.0)
    free, _ = _substep(xml, [0.5, 0.0], None, v_max=1.0, a_max=0.5)
    r, inv = _substep(xml, [0.5, 0.0], band, v_max=1.0, a_max=0.5)
    assert inv.saturated[1] and np.isfinite(inv.torque_excess[1]) and inv.torque_excess[1] > 0.0
    assert band[1][1] < r[1] <= free[1] + 1e-9
    monkeypatch.setattr(actuation, "RK4_PASSES", 0)
    r0, inv0 = _substep(xml, [0.5, 0.0], band, v_max=1.0, a_max=0.5)
    np.testing.assert_array_equal(r, r0)
    np.testing.assert_array_equal(inv.torque_excess, inv0.torque_excess)


def test_the_torque_derived_a_max_meets_condition_11():
    """Gymnasium's Ant (50 ms control steps): its motors give ~105 rad/s^2, condition (11) allows 60 at v_max = 3;
    the torque-derived a_max is lowered to what (11) allows, so the shield can be built (it raised before)."""
    env = gymnasium.make("Ant-v5")
    m = env.unwrapped.model
    dt = float(m.opt.timestep) * env.unwrapped.frame_skip
    robot = Robot.from_model(m, v_max=3.0, control_dt=dt)
    cap = _condition_11_cap(robot.limited, robot.limits.q_min, robot.limits.q_max, robot.limits.v_max, dt)
    assert robot.a_max_source == "torque"
    assert np.all(robot.limits.a_max <= cap) and np.any(robot.limits.a_max == cap)
    JointLimitShieldWrapper(gymnasium.make("Ant-v5"), v_max=3.0).close()
    # a user's a_max is never lowered: beyond (11) it is the eager error naming the bound
    np.testing.assert_array_equal(Robot.from_model(m, v_max=3.0, control_dt=dt, a_max=2 * cap).limits.a_max, 2 * cap)
    with pytest.raises(ValueError, match="condition \\(11\\)"):
        JointLimitShieldWrapper(gymnasium.make("Ant-v5"), v_max=3.0, a_max=2 * cap)
    env.close()


def _ant_campaign(steps: int):
    """Shielded Ant-v5 from starts inside its joint ranges (``start_inside``: its own reset puts the ankles 0.52 rad
    outside them, outside any guarantee), bang-bang, random and pressing policies; counts over every substep."""
    env = JointLimitShieldWrapper(gymnasium.make("Ant-v5"), v_max=3.0, start_inside=True)
    env.reset(seed=0)
    env.action_space.seed(0)
    pos = vel = corrected = sat = 0
    for i in range(steps):
        cls = (i // 50) % 3
        if cls == 0:
            a = env.action_space.high if (i // 5) % 2 else env.action_space.low
        elif cls == 1:
            a = env.action_space.sample()
        else:
            a = env.action_space.high
        _, _, term, trunc, info = env.step(a)
        pos += info["violation"]["position"] > 0
        vel += info["violation"]["velocity"] > 0
        corrected += info["shield"]["contact_corrected"] > 0
        sat += bool(info["shield"]["saturated"])
        if term or trunc:
            env.reset()
    env.close()
    return pos, vel, corrected, sat


def test_shielded_ant_keeps_its_limits(monkeypatch):
    """0 position / velocity violations in 600 steps (3 000 RK4 substeps, its feet on the floor); with the
    retakes off (the first stage's correction only, as before) the same run violates."""
    pos, vel, corrected, sat = _ant_campaign(600)
    assert corrected > 100  # the contacts were there
    assert (pos, vel, sat) == (0, 0, 0)
    monkeypatch.setattr(actuation, "RK4_PASSES", 0)
    pos0, vel0, _, _ = _ant_campaign(600)
    assert pos0 + vel0 > 0


def _reset_warnings(caught) -> list:
    return [w for w in caught if "reset state lies outside" in str(w.message)]


def test_a_reset_outside_the_ranges_is_warned_counted_and_start_inside_starts_inside():
    """Gymnasium's Ant resets its ankles ~0.5 rad outside their ranges: the wrapper warns (once per wrapper), reports
    the excess in ``info["start_violation"]`` and counts the reset; the first step from there throws the ankles back
    (MuJoCo's limit rows) at ~8-10 rad/s over ``v_max``, which no command prevents. ``start_inside=True`` moves the
    initial pose inside: no warning, no excess, and the same first step violates nothing."""
    env = JointLimitShieldWrapper(gymnasium.make("Ant-v5"), v_max=3.0)
    with pytest.warns(UserWarning, match="reset state lies outside the shielded joints' limits .*'ankle_"):
        _, info = env.reset(seed=0)
    assert info["start_violation"]["position"] > 0.4 and info["start_violation"]["velocity"] == 0.0
    assert env.step(env.action_space.high)[4]["violation"]["velocity"] > 1.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        env.reset(seed=1)
    assert not _reset_warnings(caught) and env.tally["starts_outside"] == 2

    inside = JointLimitShieldWrapper(gymnasium.make("Ant-v5"), v_max=3.0, start_inside=True)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for seed in range(3):
            _, info = inside.reset(seed=seed)
            assert info["start_violation"] == {"position": 0.0, "velocity": 0.0}
            first = inside.step(inside.action_space.high)[4]["violation"]
            assert first == {"position": 0.0, "velocity": 0.0, "torque": 0.0}
    assert not _reset_warnings(caught) and inside.tally["starts_outside"] == 0
    env.close()
    inside.close()
