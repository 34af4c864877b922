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


LEG = """
<mujoco><compiler angle="radian"/><option timestep="0.002" integrator="Euler" gravity="0 0 {g}"/>
  <worldbody>
    <body name="torso" pos="0 0 1">{base}<geom type="box" size="0.1 0.1 0.1" mass="5" contype="0" conaffinity="0"/>
      <body name="thigh"><joint name="hip" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -0.4" size="0.04" mass="1" contype="0" conaffinity="0"/>
        <body name="shin" pos="0 0 -0.4"><joint name="knee" axis="0 1 0" range="-2 0"/>
          <geom type="capsule" fromto="0 0 0 0.1 0 -0.4" size="0.03" mass="0.5" contype="0" conaffinity="0"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="hip" gear="40" ctrlrange="-1 1"/><motor joint="knee" gear="30" ctrlrange="-1 1"/></actuator>
</mujoco>"""


def _leg(floating=True, g=-9.81):
    return mujoco.MjModel.from_xml_string(LEG.format(base="<freejoint/>" if floating else "", g=g))


def test_a_floating_bases_joint_dynamics_are_what_mujoco_integrates():
    """``joint_dynamics``: with a free base, the joints' ``tau = M_s a - f_s`` is the Schur complement of the
    base's dofs (the base accelerating freely), checked against MuJoCo's own ``qacc`` at random states; the
    actuation applies the torque of that equation (the decision's torque rows keep the base held:
    ``actuation.TorqueModel``)."""
    from jaxlimits.envs.robot import joint_dynamics

    m = _leg()
    r = Robot.from_model(m, v_max=3.0)
    assert r.coupled and list(r.names) == ["hip", "knee"]
    d, rng = mujoco.MjData(m), np.random.default_rng(0)
    act = CActuation(r, m)
    full = np.zeros((m.nv, m.nv))
    for _ in range(20):
        d.qpos[:] = m.qpos0 + np.r_[rng.normal(0, 0.1, 3), 0, 0, 0, 0, rng.uniform(-0.5, 0.5), rng.uniform(-1.5, -0.2)]
        quat = rng.normal(size=4)
        d.qpos[3:7] = quat / np.linalg.norm(quat)
        d.qvel[:] = rng.normal(0, 1.0, m.nv)
        tau = rng.uniform(-20, 20, 2)
        d.ctrl[:] = 0.0
        d.qfrc_applied[:] = 0.0
        d.qfrc_applied[r.dof_adr] = tau
        mujoco.mj_forward(m, d)
        mujoco.mj_fullM(m, d, full)
        M_s, f_s = joint_dynamics(np, full, d.qfrc_passive - d.qfrc_bias, r.dof_adr, r.other_dofs, True)
        np.testing.assert_allclose(d.qacc[r.dof_adr], np.linalg.solve(M_s, tau + f_s), rtol=1e-9, atol=1e-9)
        # the fixed-base block alone (what the torque rows and a_max used before) is another equation here
        assert not np.allclose(full[np.ix_(r.dof_adr, r.dof_adr)], M_s, rtol=1e-3)
        # the actuation applies that equation's torque (unsaturated) and the joints get ``a``
        d.qfrc_applied[:] = 0.0
        a = rng.uniform(-0.5, 0.5, 2) * r.limits.a_max
        v0 = d.qvel[r.dof_adr].copy()
        _, M_eff, f_other = act.smooth_stage(d, np.zeros(m.nu))
        M_s, f_s = joint_dynamics(np, M_eff, f_other, r.dof_adr, r.other_dofs, True)
        inv, _ = act.finish_substep(d, M_eff, f_other, a)
        assert not inv.saturated.any()
        np.testing.assert_allclose(M_s @ a - f_s, r.gear * d.actuator_force, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose((d.qvel[r.dof_adr] - v0) / m.opt.timestep, a, rtol=1e-7, atol=1e-7)


def test_a_floating_bases_a_max_is_its_legs_capacity_with_the_base_held():
    """The torque-derived ``a_max`` (Alg. 4) of a floating leg is taken with its base held at ``qpos0``, as if
    welded to the world (the leg carries its weight, as in stance), not with the base free as the torque rows
    take it (there gravity would load no joint: measured, the legs then struck the floor harder than their
    motors hold; ``robot._braking_capacity``)."""
    free, welded = (Robot.from_model(_leg(floating), v_max=3.0) for floating in (True, False))
    assert free.coupled and not welded.coupled
    np.testing.assert_allclose(free.limits.a_max, welded.limits.a_max, rtol=1e-12)
    weightless = Robot.from_model(_leg(True, g=0.0), v_max=3.0)
    assert np.all(free.limits.a_max < weightless.limits.a_max)


def test_a_joint_that_cannot_brake_is_named_with_its_shortfall():
    """A hip motor too weak for the leg's weight: the eager error names it, says it cannot brake even alone, with
    the (negative) acceleration available, and what to pass instead."""
    m = _leg(floating=False)
    m.actuator_gear[0, 0] = 0.1
    with pytest.raises(
        ValueError,
        match=r"cannot brake joints \{'hip': -[0-9.]+\} \[rad/s\^2 available, braking "
        r"alone\] at the 5.0% quantile.*pass a_max= explicitly or lower v_max",
    ) as err:
        Robot.from_model(m, v_max=3.0)
    assert "knee" not in str(err.value)


CLAMP = """
<mujoco><compiler angle="radian"/><option timestep="0.002" integrator="{integrator}"/>
  <worldbody>
    <body name="l1"><joint name="j1" axis="0 1 0" range="-1 1" damping="0.3" {clamp1}/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="l2" pos="0.3 0 0"><joint name="j2" axis="0 1 0" range="-2 2" {clamp2}/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="j1" gear="{gear}" ctrlrange="-1 1" {range1}/>
    <position joint="j2" kp="60" kv="2" ctrlrange="-2 2" {range2}/></actuator>
</mujoco>"""


def _clamp_pair(integrator="Euler", gear=50.0):
    """Two models MuJoCo drives alike: joint-level ``actuatorfrcrange`` (20 N m on j1, whose motor could give 50; 4
    N m on j2) and the same limits as the actuators' own ``forcerange``."""
    joint = dict(clamp1='actuatorfrcrange="-20 20"', clamp2='actuatorfrcrange="-4 4"', range1="", range2="")
    own = dict(
        clamp1="", clamp2="", range1=f'forcerange="{-20 / abs(gear)} {20 / abs(gear)}"', range2='forcerange="-4 4"'
    )
    return tuple(
        mujoco.MjModel.from_xml_string(CLAMP.format(integrator=integrator, gear=gear, **kw)) for kw in (joint, own)
    )


@pytest.mark.parametrize("gear", [50.0, -50.0])
def test_a_joints_actuatorfrcrange_is_its_actuators_force_range(gear):
    clamped, own = (Robot.from_model(m, v_max=2.0) for m in _clamp_pair(gear=gear))
    np.testing.assert_allclose(clamped.force_range, [[-0.4, 0.4], [-4.0, 4.0]])
    np.testing.assert_array_equal(clamped.force_range, own.force_range)
    np.testing.assert_array_equal(clamped.tau_max, own.tau_max)  # the braking capacity sees the clamp
    np.testing.assert_array_equal(clamped.limits.a_max, own.limits.a_max)


@pytest.mark.parametrize("integrator", ["Euler", "implicitfast"])
def test_the_actuation_under_a_joint_force_clamp_is_that_of_the_same_forcerange(integrator):
    """The env's ``ctrl`` past the clamp (MuJoCo clamps ``qfrc_actuator``, not ``actuator_force``): the asked
    acceleration and the other forces are those of the model whose actuators carry the limit; the shield's own
    commands stay inside it, so the acceleration it decides is realised exactly in both."""
    models = _clamp_pair(integrator)
    robots = [Robot.from_model(m, v_max=2.0) for m in models]
    acts = [CActuation(r, m) for r, m in zip(robots, models)]
    datas = [mujoco.MjData(m) for m in models]
    rng = np.random.default_rng(1)
    worst, inside = 0.0, 0
    for _ in range(60):
        q, v = rng.uniform(-0.9, 0.9, 2), rng.uniform(-2.0, 2.0, 2)
        ctrl = rng.choice([-1.0, 1.0], 2) * [1.0, 2.0]  # full ctrl: 50 N m asked of j1, clamped to 20
        a = rng.uniform(-0.5, 0.5, 2) * robots[0].limits.a_max
        out = []
        for act, d, m in zip(acts, datas, models):
            d.qpos[:], d.qvel[:] = q, v
            a_des, M, f = act.smooth_stage(d, ctrl)
            inv, _ = act.finish_substep(d, M, f, a)
            out.append((a_des, f, inv.saturated, (d.qvel - v) / m.opt.timestep))
        (a_c, f_c, s_c, r_c), (a_o, f_o, s_o, r_o) = out
        np.testing.assert_allclose(a_c, a_o, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(f_c, f_o, rtol=1e-12, atol=1e-9)
        np.testing.assert_array_equal(s_c, s_o)
        np.testing.assert_allclose(r_c, r_o, rtol=1e-12, atol=1e-9)
        if not s_c.any():  # a saturated joint moves the other through M
            worst = max(worst, float(np.max(np.abs(r_c - a))))
            inside += 1
    assert inside > 20 and worst < 1e-9, (inside, worst)


@pytest.mark.parametrize(
    "clamp1, range1, gravcomp, message",
    [
        # MuJoCo clamps the actuator force and the gravity compensation together
        ('actuatorfrcrange="-20 20" actuatorgravcomp="true"', "", True, r"\['j1'\] have both actuatorfrcrange and"),
        (
            'actuatorfrcrange="-0.1 0.1"',
            'forcerange="5 10"',
            False,
            r"'j1': \(\[5.0, 10.0\], \[-0.1, 0.1\]\).*over the gear\) do not overlap",
        ),
    ],
)
def test_a_joint_force_clamp_the_shield_cannot_read_is_refused_with_the_joint(clamp1, range1, gravcomp, message):
    xml = CLAMP.format(integrator="Euler", gear=50.0, clamp1=clamp1, clamp2="", range1=range1, range2="")
    if gravcomp:
        xml = xml.replace('<body name="l1">', '<body name="l1" gravcomp="1">')
    with pytest.raises(ValueError, match=message):
        Robot.from_model(mujoco.MjModel.from_xml_string(xml), v_max=2.0)


def test_mjx_agrees_under_a_joint_force_clamp():
    """MJX clamps ``qfrc_actuator`` by ``actuatorfrcrange`` too: its actuation gives C MuJoCo's other forces and
    realises the decided acceleration (float32)."""
    import jax
    from mujoco import mjx

    from jaxlimits.envs.actuation import MjxActuation

    m = _clamp_pair()[0]
    robot = Robot.from_model(m, v_max=2.0)
    q, v, ctrl = np.array([0.3, -0.2]), np.array([0.5, -1.0]), np.array([1.0, 2.0])
    a = np.array([3.0, -5.0])
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:] = q, v
    a_c, _, f_c = CActuation(robot, m).smooth_stage(d, ctrl)
    act = MjxActuation(robot, mjx.put_model(m))

    @jax.jit
    @jax.numpy_rank_promotion("allow")  # MJX's own code relies on it
    def substep(d0):
        dd, M, f = act.smooth_stage(d0, ctrl)
        dn, inv, _ = act.finish_substep(dd, M, f, a.astype(np.float32))
        return act.asked_acceleration(dd, M), f, (dn.qvel - dd.qvel) / m.opt.timestep, inv.saturated

    d0 = mujoco.MjData(m)
    d0.qpos[:], d0.qvel[:] = q, v
    a_des, f, r, sat = jax.device_get(substep(mjx.put_data(m, d0)))
    np.testing.assert_allclose(a_des, a_c, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(f, f_c, rtol=1e-4, atol=1e-4)
    assert not sat.any()
    np.testing.assert_allclose(r, a, atol=1e-3)


GRIPPER_ARM = """
<mujoco><option timestep="0.002" integrator="{integrator}"/>
  <worldbody>
    <body name="l1"><joint name="j1" axis="0 1 0" range="-1 1" damping="0.5"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="l2" pos="0.3 0 0"><joint name="j2" axis="0 0 1" range="-2 2"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
        <body name="left" pos="0.3 0.05 0"><joint name="f1" type="slide" axis="0 1 0" range="-0.04 0.04"/>
          <geom size="0.02" mass="0.3"/></body>
        <body name="right" pos="0.3 -0.05 0"><joint name="f2" type="slide" axis="0 -1 0" range="-0.04 0.04"/>
          <geom size="0.02" mass="0.3"/></body>
      </body>
    </body>
  </worldbody>
  <tendon>
    <fixed name="split"><joint joint="f1" coef="0.5"/><joint joint="f2" coef="0.5"/></fixed>
    <fixed name="squeeze" damping="{tendon_damping}"><joint joint="f1" coef="1"/><joint joint="f2" coef="-1"/></fixed>
  </tendon>
  <actuator>
    <motor joint="j1" gear="50" ctrlrange="-1 1"/>
    <position joint="j2" kp="200" kv="4" ctrlrange="-2 2" forcerange="-50 50"/>
    <general tendon="split" biastype="affine" gainprm="400" biasprm="0 -400 -60" ctrlrange="-0.04 0.04"/>
  </actuator>
</mujoco>"""


@pytest.mark.parametrize("integrator", ["Euler", "implicitfast"])
def test_a_grippers_fixed_tendon_servo_and_tendon_damping_enter_the_implicit_damping(integrator):
    """Menagerie's grippers (xArm7, Panda's hand, Robotiq) drive their fingers through a fixed tendon with a servo's
    velocity bias; implicitfast integrates it, and a fixed tendon's damping, implicitly: ``kv m m^T`` and
    ``d c c^T``, which couple the fingers' dofs, and through ``M`` the arm's realised acceleration (such models were
    refused). The shielded arm's acceleration is realised exactly with the gripper's servo commanded anywhere; with
    those terms left out it is not (so the check can fail)."""
    m = mujoco.MjModel.from_xml_string(GRIPPER_ARM.format(integrator=integrator, tendon_damping=3.0))
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    r = Robot.from_model(m, v_max=2.0)
    assert r.names == ("j1", "j2")
    f1, f2 = int(m.jnt_dofadr[m.joint("f1").id]), int(m.jnt_dofadr[m.joint("f2").id])
    D = r.implicit_damping
    if integrator == "implicitfast":
        # the servo's 60 * 0.5 * 0.5 on the split plus the squeeze's damping 3 * 1 * 1; between the fingers (siblings:
        # outside M's sparsity) MuJoCo keeps nothing, and neither does the shield
        np.testing.assert_allclose(D[f1, f1], 60 * 0.25 + 3.0)
        assert D[f1, f2] == 0.0
    else:  # Euler: the joints' own damping only
        assert D[f1, f2] == 0.0 and D[f1, f1] == 0.0

    def worst_error(act):
        d = mujoco.MjData(m)
        rng = np.random.default_rng(0)
        worst = 0.0
        for _ in range(60):
            ctrl = np.array([0.0, 0.0, rng.uniform(-0.04, 0.04)])
            a = rng.uniform(-0.3, 0.3, r.n) * r.limits.a_max
            v0 = d.qvel[r.dof_adr].copy()
            _, M, f = act.smooth_stage(d, ctrl)
            act.finish_substep(d, M, f, a)
            worst = max(worst, np.max(np.abs((d.qvel[r.dof_adr] - v0) / m.opt.timestep - a)))
        return worst

    assert worst_error(CActuation(r, m)) < 1e-9
    if integrator == "implicitfast":
        act = CActuation(r, m)
        act._damping[[f1, f2], [f1, f2]] = 0.0  # the gripper's servo and tendon damping left out (as before)
        assert worst_error(act) > 1e-6


def test_mjx_keeps_the_whole_damping_derivative_and_its_actuation_realises_the_acceleration():
    """MJX's implicitfast keeps the whole derivative (the fingers' coupling through the tendons included; C MuJoCo keeps
    ``M``'s sparsity): ``MjxActuation`` uses MJX's, and realises the decided acceleration (float32)."""
    import jax
    from mujoco import mjx

    from jaxlimits.envs.actuation import MjxActuation
    from jaxlimits.envs.robot import _implicit_damping

    m = mujoco.MjModel.from_xml_string(GRIPPER_ARM.format(integrator="implicitfast", tendon_damping=3.0))
    m.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONSTRAINT)
    r = Robot.from_model(m, v_max=2.0)
    f1, f2 = int(m.jnt_dofadr[m.joint("f1").id]), int(m.jnt_dofadr[m.joint("f2").id])
    sysm = mjx.put_model(m)
    np.testing.assert_allclose(np.asarray(_implicit_damping(sysm, sysm, np, "mjx"))[f1, f2], 60 * 0.25 - 3.0)
    a = np.array([20.0, -100.0], np.float32)
    ctrl = np.array([0.0, 0.0, 0.04])
    d0 = mujoco.MjData(m)
    d0.qvel[:] = [0.3, -1.5, 2.0, -2.0]  # the fingers sliding the same way: the arm feels their coupling

    def miss(act):
        @jax.jit
        @jax.numpy_rank_promotion("allow")  # MJX's own code relies on it
        def substep(d):
            dd, M, f = act.smooth_stage(d, ctrl)
            dn, inv, _ = act.finish_substep(dd, M, f, a)
            return (dn.qvel - dd.qvel)[np.asarray(r.dof_adr)] / m.opt.timestep, inv.saturated

        realised, sat = jax.device_get(substep(mjx.put_data(m, d0)))
        assert not sat.any()
        return float(np.max(np.abs(realised - a)))

    assert miss(MjxActuation(r, sysm)) < 2e-3
    c_model = MjxActuation(r, sysm)
    c_model._damping = (m.opt.timestep * r.implicit_damping).astype(np.float32)  # C MuJoCo's sparsity: wrong here
    assert miss(c_model) > 0.1


def test_a_velocity_bias_through_a_spatial_tendon_is_refused_naming_it():
    xml = GRIPPER_ARM.format(integrator="implicitfast", tendon_damping=0.0).replace(
        '<fixed name="split"><joint joint="f1" coef="0.5"/><joint joint="f2" coef="0.5"/></fixed>',
        '<spatial name="split"><site site="s1"/><site site="s2"/></spatial>',
    )
    xml = xml.replace(
        '<geom size="0.02" mass="0.3"/></body>\n        <body name="right"',
        '<geom size="0.02" mass="0.3"/><site name="s1"/></body>\n        <body name="right"',
    )
    xml = xml.replace(
        '<geom size="0.02" mass="0.3"/></body>\n      </body>',
        '<geom size="0.02" mass="0.3"/><site name="s2"/></body>\n      </body>',
    )
    with pytest.raises(ValueError, match="spatial tendon 'split'"):
        Robot.from_model(mujoco.MjModel.from_xml_string(xml), v_max=2.0)
