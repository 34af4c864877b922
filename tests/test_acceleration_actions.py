"""Joint-acceleration actions on any robot (``envs/acceleration_actions.py``, ``Reach(action="acceleration")``) and the
project's planar arm under the one shield: the ``ctrl`` computed realises the asked acceleration in C MuJoCo (an
independent integrator), ``JointLimitShield`` over that task decides as ``SafetyWrapper`` over ``ArmReach`` at the same
states, never violates under the adversarial policies, and bad input is an eager error naming it."""

from __future__ import annotations

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import functools
import warnings

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.acceleration_actions import AccelerationActions
from jaxlimits.envs.adversarial import shield_rollout
from jaxlimits.envs.arm import ASSETS, make_panda_reach, make_planar_reach
from jaxlimits.envs.reach import Reach
from jaxlimits.envs.safety import SafetyWrapper

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from brax.io import mjcf


def _c_mujoco_acceleration(mjm, q, v, ctrl):
    """``(nv,)`` the acceleration one C MuJoCo substep realises from ``(q, v)`` with ``ctrl``: ``(v+ - v) / h``, and
    ``d`` after it (its constraint rows)."""
    d = mujoco.MjData(mjm)
    d.qpos[:], d.qvel[:], d.ctrl[:] = np.asarray(q), v, np.asarray(ctrl, np.float64)
    mujoco.mj_step(mjm, d)
    return (d.qvel - v) / mjm.opt.timestep, d


@pytest.mark.parametrize(
    "xml, scale, rtol",
    [
        ("planar3.xml", None, 1e-5),  # motors, Euler; scale from jaxlimits_a_max
        # position servos (kp, kv: implicit damping), implicitfast: float32 ctrl rounding on stiff servos
        ("ur5e.xml", 5.0, 2e-3),
    ],
)
def test_the_ctrl_realises_the_asked_acceleration_in_c_mujoco(xml, scale, rtol):
    env = Reach(ASSETS / xml, action="acceleration", acceleration_scale=scale)
    mjm = env.mj_model
    acc = env._accelerations
    ctrl_of, reset = jax.jit(env.ctrl), jax.jit(env.reset)
    rng = np.random.default_rng(0)
    dofs = mjm.jnt_dofadr[mjm.actuator_trnid[:, 0]]
    checked = 0
    for i in range(8):
        ps = reset(jax.random.PRNGKey(i)).pipeline_state
        v = rng.uniform(-1.0, 1.0, mjm.nv).astype(np.float32)
        action = rng.uniform(-0.3, 0.3, mjm.nu).astype(np.float32)
        ctrl = np.asarray(ctrl_of(ps.replace(qvel=jnp.asarray(v)), action), np.float64)
        lo, hi = mjm.actuator_ctrlrange.T
        assert np.all((ctrl > lo) & (ctrl < hi)), "the test's actions should not saturate"
        realised, d = _c_mujoco_acceleration(mjm, ps.qpos, v, ctrl)
        assert d.ncon == 0 and d.nefc == 0
        want = np.zeros(mjm.nv)
        want[dofs] = action * acc.scale
        np.testing.assert_allclose(realised, want, atol=rtol * acc.scale.max())
        checked += 1
    assert checked == 8


def _system(xml: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return mjcf.load_model(mujoco.MjModel.from_xml_string(xml))


_ARM = """<mujoco><option timestep="0.002"/><worldbody><body><joint name="j1" type="hinge" range="-1 1"/>
<geom size="0.1" mass="1"/><body pos="0 0 0.3"><joint name="j2" type="hinge" range="-1 1"/><geom size="0.1" mass="1"/>
</body></body></worldbody><actuator>{}</actuator>{}</mujoco>"""


def test_bad_input_is_an_eager_error_naming_it():
    two_motors = '<motor name="m1" joint="j1" ctrlrange="-9 9"/><motor name="m2" joint="j2" ctrlrange="-9 9"/>'
    assert np.allclose(AccelerationActions(_system(_ARM.format(two_motors, "")), 3.0).scale, 3.0)
    numerics = '<custom><numeric name="jaxlimits_a_max" data="4 7"/></custom>'
    np.testing.assert_allclose(AccelerationActions(_system(_ARM.format(two_motors, numerics))).scale, [4, 7])
    with pytest.raises(ValueError, match="acceleration_scale .* or the MJCF custom numeric jaxlimits_a_max"):
        AccelerationActions(_system(_ARM.format(two_motors, "")))
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="acceleration_scale must be finite and > 0"):
            AccelerationActions(_system(_ARM.format(two_motors, "")), bad)
    with pytest.raises(ValueError, match=r"exactly one actuator; joints \{name: actuators driving it\}: \{'j2': 0\}"):
        AccelerationActions(_system(_ARM.format('<motor name="m1" joint="j1"/>', "")), 1.0)
    doubled = two_motors + '<motor name="m3" joint="j2"/>'
    with pytest.raises(ValueError, match=r"exactly one actuator; .*: \{'j2': 2\}"):
        AccelerationActions(_system(_ARM.format(doubled, "")), 1.0)
    filtered = '<motor name="m1" joint="j1"/><general name="m2" joint="j2" dyntype="filter" dynprm="0.1"/>'
    with pytest.raises(ValueError, match="actuator 'm2' cannot be inverted .*dyntype"):
        AccelerationActions(_system(_ARM.format(filtered, "")), 1.0)
    with pytest.raises(ValueError, match="acceleration_scale is for action='acceleration', not 'ctrl'"):
        Reach(ASSETS / "planar3.xml", acceleration_scale=1.0)
    with pytest.raises(ValueError, match="jaxlimits_a_max"):  # the servo Panda ships no a_max numeric
        Reach(ASSETS / "panda_servo.xml", action="acceleration")


@functools.lru_cache(maxsize=None)
def _pair(xml: str):
    """``(limits, SafetyWrapper(ArmReach), JointLimitShield(Reach(action="acceleration")))`` over the same arm and the
    same action scale; ``limits`` the arm's own (its torque-derived ``a_max`` is given to the one shield)."""
    arm = {"planar3.xml": make_planar_reach, "panda.xml": make_panda_reach}[xml]()
    own = arm.limits
    reach = Reach(ASSETS / xml, action="acceleration", acceleration_scale=own.a_max, n_frames=arm.frame_skip)
    new = JointLimitShield(reach, a_max=own.a_max, torque_limits=False)
    arm.limits = new.decide.limits  # the decision compared on the same numbers (their differences: the first test)
    return own, SafetyWrapper(arm, "viability"), new


@pytest.fixture(scope="module", params=["planar3.xml", "panda.xml"])
def arm_pair(request):
    return _pair(request.param)


def test_the_one_shield_decides_as_the_safety_wrapper_on_the_projects_arms(arm_pair):
    """The one shield reads the arm's limits from the model as ``ArmReach`` does, up to Brax's float32 copy of the
    ranges and the realisation margin (``joint_shield.QUANTUM_SAFETY``: ~1e-6 of ``v_max`` for these motors); given
    the same numbers, its decision is the ``SafetyWrapper``'s, states on and past the limits included."""
    own, old, new = arm_pair
    lim = new.decide.limits
    for field in ("q_min", "q_max", "a_max", "j_max"):
        np.testing.assert_allclose(getattr(new.robot.limits, field), getattr(own, field), rtol=1e-7, err_msg=field)
    np.testing.assert_allclose(lim.v_max, own.v_max, rtol=3e-6)
    assert np.all(lim.v_max < own.v_max)
    assert new.decide.dt == pytest.approx(old.dt_bounds) and new.decide.substeps == old.substeps
    assert new.decide.integrator == old.env.integrator
    rng = np.random.default_rng(1)
    B, n = 2048, old.env.n
    q_min, q_max, v_max, a_max = (np.asarray(x, np.float32) for x in (lim.q_min, lim.q_max, lim.v_max, lim.a_max))
    # positions over the whole range and on its ends, velocities up to and a little past v_max (non-viable states)
    q = rng.uniform(q_min, q_max, (B, n)).astype(np.float32)
    q[: B // 4] = np.where(rng.random((B // 4, n)) < 0.5, q_min, q_max)
    v = (rng.uniform(-1.05, 1.05, (B, n)) * v_max).astype(np.float32)
    a_des = (rng.uniform(-1.5, 1.5, (B, n)) * a_max).astype(np.float32)
    states = jax.jit(jax.vmap(old.env.reset_to))(q, v, np.zeros((B, 3), np.float32))
    assert np.array_equal(np.asarray(states.pipeline_state.qpos), q)
    a_old, b_old = jax.jit(jax.vmap(old.shield))(states, a_des)
    dec = jax.jit(jax.vmap(new.decide))(q, v, a_des)
    for name, x, y in (
        ("a_safe", dec.a_safe, a_old),
        ("lower", dec.lower, b_old.lower),
        ("upper", dec.upper, b_old.upper),
    ):
        gap = np.max(np.abs(np.asarray(x) - np.asarray(y)) / a_max)
        assert gap < 1e-5, (name, gap)  # [a_max]
    np.testing.assert_array_equal(dec.viable, b_old.viable)
    assert 0.05 < np.mean(~np.asarray(b_old.viable)) < 0.9  # the sample holds both kinds


def test_the_planar_arm_under_the_one_shield_never_violates():
    *_, shielded = _pair("planar3.xml")
    out = shield_rollout(shielded, batch=16, steps=150)
    for k in ("position", "velocity", "nonviable", "nonfinite", "saturated"):
        assert out[f"count/{k}"] == 0, (k, out)
    assert out["max/accel_error"] < 1e-3 * float(np.max(shielded.robot.limits.a_max)), out
    reach = Reach(ASSETS / "planar3.xml", action="acceleration")
    bare = shield_rollout(JointLimitShield(reach, method="none", torque_limits=False), batch=16, steps=150)
    assert bare["count/position"] > 0 and bare["count/velocity"] > 0, bare


@pytest.mark.parametrize("method", ["jerk", "viability"])
def test_the_one_shield_measures_the_jerk_where_the_robot_has_a_jerk_limit(method):
    """``info["violation"]["jerk"]`` = ``max |a_safe - a_prev| - j_max dt`` (``ArmReach``'s measure), recomputed here
    from the decisions a rollout of bang-bang actions took: 0 at every step under the jerk shield, positive under
    viability (which does not bound the jerk); a robot without ``j_max`` records none."""
    reach = Reach(ASSETS / "planar3.xml", action="acceleration")
    env = JointLimitShield(reach, method=method)
    assert env.violations == ("position", "velocity", "torque", "jerk")
    j_step = np.asarray(env.robot.limits.j_max, np.float32) * np.float32(env.decide.dt)
    batch, steps = 8, 60
    signs = np.where(np.arange(steps)[:, None, None] // 7 % 2 == 0, 1.0, -1.0) * np.where(
        np.arange(batch)[None, :, None] % 2 == 0, 1.0, -1.0
    )
    actions = jnp.asarray(np.broadcast_to(signs, (steps, batch, env.action_size)), jnp.float32)

    @jax.jit
    def run(key):
        def body(state, action):
            nxt = jax.vmap(env.step)(state, action)
            a_prev, a_safe = state.info["shield_a_prev"], nxt.info["shield_a_prev"]
            return nxt, (nxt.info["violation"]["jerk"], jnp.max(jnp.abs(a_safe - a_prev) - j_step[None], axis=-1))

        return jax.lax.scan(body, jax.vmap(env.reset)(jax.random.split(key, batch)), actions)[1]

    recorded, recomputed = (np.asarray(x) for x in run(jax.random.PRNGKey(0)))
    np.testing.assert_array_equal(recorded, np.maximum(recomputed, 0.0))
    if method == "jerk":
        assert recorded.max() == 0.0
    else:
        assert (recorded > 0).mean() > 0.1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the torque-derived a_max's quantile notice
        no_jerk_limit = JointLimitShield(Reach(ASSETS / "ur5e.xml"), v_max=2.0)  # no j_max in its MJCF
    assert no_jerk_limit.violations == ("position", "velocity", "torque")


def test_the_ctrl_follows_the_system_it_is_given():
    """A domain randomisation's System (gears doubled, joint damping added: Euler's implicit damping) is the one the
    ``ctrl`` is computed for, checked against C MuJoCo with the same changes; the construction's would miss."""
    env = Reach(ASSETS / "planar3.xml", action="acceleration")
    mjm = mujoco.MjModel.__copy__(env.mj_model)
    mjm.actuator_gear[:, 0] *= 2.0
    mjm.dof_damping[:] = 0.5
    sys = env.sys.tree_replace(
        {"actuator_gear": jnp.asarray(mjm.actuator_gear), "dof_damping": jnp.asarray(mjm.dof_damping)}
    )
    ps = jax.jit(env.reset)(jax.random.PRNGKey(0)).pipeline_state
    v = np.array([0.8, -0.5, 1.2], np.float32)
    ps = ps.replace(qvel=jnp.asarray(v))
    action = np.array([0.2, -0.1, 0.15], np.float32)
    want = action * env._accelerations.scale
    realised = {}
    for name, system in (("given", sys), ("construction", env.sys)):
        ctrl = jax.jit(lambda p, a, s=system: env._accelerations.ctrl(s, p, a))(ps, action)
        realised[name], _ = _c_mujoco_acceleration(mjm, ps.qpos, v, ctrl)
    np.testing.assert_allclose(realised["given"], want, atol=1e-4 * want.max() + 1e-4)
    assert np.max(np.abs(realised["construction"] - want)) > 0.1
