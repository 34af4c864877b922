"""The contact correction of ``actuation``: where a contact would push a substep's realised acceleration out of
the decision's bounds, the actuators get the torque that holds it at the bounds' edge (one Newton step on the
constraint solver's problem), in C MuJoCo (float64) and MJX (float32); where they lack the force, that is a
saturation, counted with the torque they lacked. Fails without the correction (the contact's push is far
outside the band)."""

import jaxlimits.envs  # noqa: F401

import jax
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from jaxlimits.envs.actuation import CActuation, MjxActuation, other_rows_on_trees
from jaxlimits.envs.robot import Robot

# a sphere on two actuated slides (x, z), pressed 5 mm into the floor: the contact pushes it up and, through
# friction, couples x; gravity off so the contact is the only disturbance
FLOOR = """
<mujoco><option timestep="0.002" gravity="0 0 0" integrator="{integrator}"/>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <body pos="0 0 0.045">
      <joint name="x" type="slide" axis="1 0 0" range="-1 1" damping="0.5"/>
      <joint name="z" type="slide" axis="0 0 1" range="-1 1"/>
      <geom size="0.05" mass="1"/>
    </body>
  </worldbody>
  <actuator>
    <motor joint="x" ctrlrange="-1 1" gear="{gear}"/>
    <motor joint="z" ctrlrange="-1 1" gear="{gear}"/>
  </actuator>
</mujoco>"""
BAND = (np.array([-1.0, -1.0]), np.array([1.0, 1.0]))  # [m/s^2]
A_SAFE = np.array([0.5, 0.0])  # the decision: accelerate along x, hold z


def _model(integrator="Euler", gear=400.0):
    mjm = mujoco.MjModel.from_xml_string(FLOOR.format(integrator=integrator, gear=gear))
    return mjm, Robot.from_model(mjm, v_max=1.0, a_max=2.0)


def _c_substep(mjm, robot, band):
    d = mujoco.MjData(mjm)
    act = CActuation(robot, mjm)
    _, M, f = act.smooth_stage(d, np.zeros(mjm.nu))
    v0 = d.qvel.copy()
    inv, out = act.finish_substep(d, M, f, A_SAFE, band)
    return (d.qvel - v0) / mjm.opt.timestep, inv, out


@pytest.mark.parametrize("integrator", ["Euler", "implicitfast"])
def test_c_mujoco_holds_the_band_against_a_contact(integrator):
    mjm, robot = _model(integrator)
    r_free, _, out_free = _c_substep(mjm, robot, None)
    assert out_free is None and r_free[1] > 5.0  # the uncorrected push (~12 m/s^2): far above the band's 1 m/s^2
    r, inv, out = _c_substep(mjm, robot, BAND)
    assert out is not None and out[1] > 5.0  # measured before the correction
    assert not np.any(inv.saturated)
    # the corrected substep: at the band's edge on z (the contact still pushes, as far as the band allows), x
    # kept inside the band
    assert abs(r[1] - BAND[1][1]) < 1e-6, r
    assert BAND[0][0] - 1e-9 <= r[0] <= BAND[1][0] + 1e-9, r


def test_c_mujoco_counts_what_the_actuators_lack():
    mjm, robot = _model(gear=2.0)  # 2 N: not enough to hold the sphere against the contact
    r, inv, out = _c_substep(mjm, robot, BAND)
    assert inv.saturated[1] and inv.torque_excess[1] > 0.0
    assert r[1] > BAND[1][1]  # the rest of the push goes through: a violation, counted by the wrapper


def test_mjx_agrees_with_c_mujoco():
    mjm, robot = _model()
    r_c, inv_c, _ = _c_substep(mjm, robot, BAND)
    sys = mjx.put_model(mjm)
    act = MjxActuation(robot, sys)

    @jax.jit
    @jax.numpy_rank_promotion("allow")  # MJX's collision code relies on it
    def substep(d0):
        d, M, f = act.smooth_stage(d0, d0.ctrl)
        band = tuple(np.float32(b) for b in BAND)
        dn, inv, out = act.finish_substep(d, M, f, A_SAFE.astype(np.float32), band)
        return (dn.qvel - d.qvel) / mjm.opt.timestep, inv, out

    r, inv, out = jax.device_get(substep(mjx.put_data(mjm, mujoco.MjData(mjm))))
    assert out[1] > 5.0
    assert not np.any(inv.saturated)
    np.testing.assert_allclose(r, r_c, atol=2e-2)  # float32 over a stiff contact (D ~ 1e5)
    assert r[1] <= BAND[1][1] + 2e-2
    np.testing.assert_allclose(inv.ctrl, inv_c.ctrl, rtol=1e-3, atol=1e-4)


# the sphere lifted off the floor, and a free box resting on it: a contact, but in another kinematic tree
TWO_TREES = FLOOR.replace('<body pos="0 0 0.045">', '<body pos="0 0 0.3">').replace(
    "</worldbody>", '<body pos="0.5 0 0.05"><freejoint/><geom type="box" size="0.05 0.05 0.05"/></body></worldbody>'
)


@pytest.mark.parametrize("pressed", [False, True])
def test_c_mujoco_checks_only_contacts_on_the_shielded_trees(pressed):
    """A contact in another tree (the box on the floor) cannot move the shielded dofs (M is block-diagonal over
    trees): the check is skipped and the realised acceleration is the inversion's, exactly; a contact on the
    shielded tree is checked and corrected as above."""
    xml = TWO_TREES.replace('<body pos="0 0 0.3">', '<body pos="0 0 0.045">') if pressed else TWO_TREES
    mjm = mujoco.MjModel.from_xml_string(xml.format(integrator="Euler", gear=400.0))
    robot = Robot.from_model(mjm, v_max=1.0, a_max=2.0)
    assert robot.names == ("x", "z")
    d = mujoco.MjData(mjm)
    act = CActuation(robot, mjm)
    _, M, f = act.smooth_stage(d, np.zeros(mjm.nu))
    assert d.ncon >= 1  # the box rests on the floor in both
    assert act._rows_touch_trees(d) == pressed
    v0 = d.qvel[:2].copy()
    _, out = act.finish_substep(d, M, f, A_SAFE, BAND)
    r = (d.qvel[:2] - v0) / mjm.opt.timestep
    if pressed:
        assert out is not None and out[1] > 5.0 and abs(r[1] - BAND[1][1]) < 1e-6, (out, r)
    else:
        assert out is None
        np.testing.assert_allclose(r, A_SAFE, atol=1e-9)


def test_the_torque_box_moves_the_correction_to_the_joints_that_can_give_it(x64):
    """``contact_correction(..., torque_box=)``: a contact row couples two dofs (``H = M + J^T D J``); dof 0
    is pushed out of its band and its motor has no torque left. The plain step asks dof 0's motor for the
    missing torque; with the box, the answer stays inside what the motors can add and still brings both
    realised accelerations into the band (dof 1, inside, gives way within it); a box that cannot do it
    keeps the box and misses the band least."""
    import jax.numpy as jnp

    from jaxlimits.envs.actuation import contact_correction

    M = jnp.eye(2)
    J = jnp.array([[1.0, 1.0]])
    D = jnp.array([4.0])
    dofs = np.arange(2)
    qfrc = jnp.array([3.0, 0.5])  # realised r = M^-1 qfrc = (3, 0.5)
    band = (jnp.array([-1.0, -10.0]), jnp.array([1.0, 10.0]))
    H_inv = np.linalg.inv(np.eye(2) + 4.0 * np.ones((2, 2)))
    plain, out, _, _ = contact_correction(jnp, dofs, M, M, J, D, qfrc, band)
    np.testing.assert_allclose(out, [2.0, 0.0])
    np.testing.assert_allclose(np.array([3.0, 0.5]) + H_inv @ np.asarray(plain), [1.0, 0.5], atol=1e-9)
    assert plain[0] < -1.0  # dof 0's motor would have to give more than it has

    box = (jnp.array([-1.0, -30.0]), jnp.array([1.0, 30.0]))
    dtau, _, _, _ = contact_correction(jnp, dofs, M, M, J, D, qfrc, band, torque_box=box)
    r_new = np.array([3.0, 0.5]) + H_inv @ np.asarray(dtau)
    assert np.all(np.asarray(dtau) >= np.asarray(box[0]) - 1e-9) and np.all(
        np.asarray(dtau) <= np.asarray(box[1]) + 1e-9
    )
    assert np.all(r_new >= np.asarray(band[0]) - 1e-5) and np.all(r_new <= np.asarray(band[1]) + 1e-5), r_new

    # C MuJoCo's path (NumPy in, the same QP compiled in float64) gives the same answer; an unbounded actuator
    # (an infinite side) is boxed far out, and the band met leaves no miss
    as_np = [np.asarray(x, np.float64) for x in (M, J, D, qfrc)]
    fix = contact_correction(np, dofs, as_np[0], as_np[0], as_np[1], as_np[2], as_np[3], band, torque_box=box)
    np.testing.assert_allclose(fix.dtau, np.asarray(dtau), rtol=1e-9, atol=1e-9)
    assert np.all(fix.miss == 0)
    free = (jnp.array([-1.0, -np.inf]), jnp.array([1.0, np.inf]))
    fix = contact_correction(jnp, dofs, M, M, J, D, qfrc, band, torque_box=free)
    r_new = np.array([3.0, 0.5]) + H_inv @ np.asarray(fix.dtau)
    assert np.all(np.isfinite(fix.dtau)) and np.all(np.asarray(fix.miss) == 0), fix
    assert np.all(r_new >= np.asarray(band[0]) - 1e-5) and np.all(r_new <= np.asarray(band[1]) + 1e-5), r_new

    tight = (jnp.array([-0.1, -0.1]), jnp.array([0.1, 0.1]))
    dtau, _, _, miss = contact_correction(jnp, dofs, M, M, J, D, qfrc, band, torque_box=tight)
    np.testing.assert_allclose(np.asarray(dtau), [-0.1, 0.1], atol=1e-6)  # the box holds: its corner nearest the band
    # the miss it predicts: dof 0 still over its band by what the box could not take
    r_new = np.array([3.0, 0.5]) + H_inv @ np.asarray(dtau)
    np.testing.assert_allclose(np.asarray(miss), [r_new[0] - 1.0, 0.0], atol=1e-6)
    assert miss[0] > 1.0


def test_the_inset_aims_a_pushed_dof_inside_the_band_and_leaves_roundoff_at_the_edge(x64):
    """``contact_correction(..., inset=)`` (MJX's float32 passes): a dof pushed out by more than the inset is aimed
    the inset inside the band's edge (the residual of an inexact solve then stays inside); one out by less
    (roundoff at the decision's own edge) is brought to the edge as without it; ``out`` is measured from the edge
    either way; a band narrower than two insets is aimed at its middle."""
    import jax.numpy as jnp

    from jaxlimits.envs.actuation import contact_correction

    M, J, D = jnp.eye(3), jnp.zeros((1, 3)), jnp.zeros(1)  # no active row: G = I
    dofs = np.arange(3)
    band = (jnp.array([-1.0, -1.0, 0.0]), jnp.array([1.0, 1.0, 0.01]))
    qfrc = jnp.array([3.0, -1.0 - 1e-7, 0.5])  # dof 0 pushed 2 over, dof 1 1e-7 under, dof 2 over a narrow band
    inset = jnp.full(3, 0.05)
    dtau, out, _, _ = contact_correction(jnp, dofs, M, M, J, D, qfrc, band, inset=inset)
    np.testing.assert_allclose(out, [2.0, -1e-7, 0.49], atol=1e-12)
    np.testing.assert_allclose(np.asarray(qfrc) + np.asarray(dtau), [0.95, -1.0, 0.005], atol=1e-12)
    plain, _, _, _ = contact_correction(jnp, dofs, M, M, J, D, qfrc, band)
    np.testing.assert_allclose(np.asarray(qfrc) + np.asarray(plain), [1.0, -1.0, 0.01], atol=1e-12)


# a cart (the shielded slide) under a pole whose hinge (not shielded, no actuator) is pressed 1 degree past its
# 20 degree limit: the limit's constraint force acts on the hinge and, through M, on the cart, with no contact
CARTPOLE = """<mujoco><option timestep="0.01" integrator="{integrator}"/>
  <worldbody><body><joint name="slider" type="slide" axis="1 0 0" range="-1 1"/>
      <geom type="box" size="0.1 0.1 0.05" mass="1" contype="0" conaffinity="0"/>
      <body><joint name="hinge" type="hinge" axis="0 1 0" range="-20 20"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.05" mass="1" contype="0" conaffinity="0"/></body></body>
    {other}</worldbody>
  <actuator><motor joint="slider" ctrlrange="-1 1" gear="100"/></actuator></mujoco>"""
BAND_1 = (np.array([-1.0]), np.array([1.0]))


def _cartpole(integrator="Euler", other=""):
    mjm = mujoco.MjModel.from_xml_string(CARTPOLE.format(integrator=integrator, other=other))
    d = mujoco.MjData(mjm)
    d.qpos[1], d.qvel[1] = np.deg2rad(21.0), 1.0
    return mjm, Robot.from_model(mjm, v_max=1.0, a_max=2.0), d


def test_other_rows_on_the_shielded_trees_are_found():
    mjm, robot, _ = _cartpole()
    assert robot.names == ("slider",) and other_rows_on_trees(mjm, robot)
    # the hinge's own tree, not the cart's: its limit cannot reach the cart
    apart = CARTPOLE.replace('<body><joint name="hinge"', '</body><body pos="2 0 0"><joint name="hinge"').replace(
        "</body></body>\n    {other}", "</body>\n    {other}"
    )
    mjm2 = mujoco.MjModel.from_xml_string(apart.format(integrator="Euler", other=""))
    assert not other_rows_on_trees(mjm2, Robot.from_model(mjm2, v_max=1.0, a_max=2.0))


@pytest.mark.parametrize("integrator", ["Euler", "implicitfast"])
def test_an_unshielded_joints_limit_is_corrected_like_a_contact(integrator):
    """Brax's inverted pendulum broke the cart's limits without a contact or a saturation (415 of 3 200 adversarial
    steps): its pole's hinge limit pushed the cart through ``M``, and only contacts were corrected."""
    mjm, robot, d = _cartpole(integrator)
    act = CActuation(robot, mjm)
    _, M, f = act.smooth_stage(d, np.zeros(mjm.nu))
    assert d.ncon == 0 and d.nefc == 1
    v0 = d.qvel[0]
    inv, out = act.finish_substep(d, M, f, np.array([0.5]), BAND_1)
    r = (d.qvel[0] - v0) / mjm.opt.timestep
    assert out is not None and out[0] > 10.0  # uncorrected: ~21.5 m/s^2 against a band of 1
    assert abs(r - 1.0) < 1e-9 and not inv.saturated[0]

    mjm, robot, d = _cartpole(integrator)
    act = MjxActuation(robot, mjx.put_model(mjm))

    @jax.jit
    @jax.numpy_rank_promotion("allow")
    def substep(d0):
        d, M, f = act.smooth_stage(d0, d0.ctrl)
        band = tuple(np.float32(b) for b in BAND_1)
        dn, inv, out = act.finish_substep(d, M, f, np.float32([0.5]), band)
        return (dn.qvel - d.qvel) / mjm.opt.timestep, out

    r, out = jax.device_get(substep(mjx.put_data(mjm, d)))
    assert out[0] > 10.0 and abs(r[0] - 1.0) < 1e-3
