"""SafeAcceleration, the shield's decision: the clip without torque limits, the torque-space decision
(realisable, the clip where the clip is realisable), its conflict rule (the acceleration and jerk limits
give way before position, velocity and viability; a servo that cannot hold back gravity brakes harder
than a_max), the NaN guard; jit = eager, float32 and float64."""

import jaxlimits.envs  # noqa: F401

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import jaxlimits as jl
from jaxlimits.envs.actuation import TorqueModel
from jaxlimits.envs.joint_shield import SafeAcceleration
from jaxlimits.envs.robot import Robot

TWO = """
<mujoco><option timestep="0.002"/>
  <worldbody>
    <body><joint name="j1" axis="0 1 0" range="-1 1"/><geom size="0.05" mass="1"/>
      <body pos="0.3 0 0"><joint name="j2" axis="0 1 0" range="-1 1"/><geom size="0.05" mass="1"/></body>
    </body>
  </worldbody>
  <actuator><motor joint="j1" ctrlrange="-10 10"/><motor joint="j2" ctrlrange="-10 10"/></actuator>
</mujoco>"""
A_MAX = np.array([2.0, 3.0])


@pytest.fixture(scope="module")
def decide():
    robot = Robot.from_model(mujoco.MjModel.from_xml_string(TWO), v_max=1.5, a_max=A_MAX, j_max=200.0)
    return {m: SafeAcceleration(robot, 5, m) for m in ("viability", "jerk")}


def test_jerk_bounds_that_cannot_recover_are_refused_at_construction():
    """``method="jerk"`` with too little braking for the range (here a_max 0.01 rad/s^2 at j_max 200): the bounds'
    own check raises, at construction, not at the first trace of a step (a Brax env's first jitted call)."""
    robot = Robot.from_model(mujoco.MjModel.from_xml_string(TWO), v_max=1.5, a_max=0.01, j_max=200.0)
    SafeAcceleration(robot, 5, "viability")  # viability has no such condition
    with pytest.raises(ValueError, match="jerk-aware bounds are exact only with room to recover"):
        SafeAcceleration(robot, 5, "jerk")


def _torque(dtype, M, f, lo, hi):
    return TorqueModel(*(jnp.asarray(x, dtype) for x in (M, f, lo, hi)))


def _pinched_state(decide, dtype):
    """Joint 1 moving up at the edge of the viability kernel (its bounds pinched at ``-a_max``); joint 2 free."""
    d = decide["viability"]
    v1 = 1.0
    # the braking distance of the semi-implicit model at a_max, from q_max back: a state on the kernel's edge
    lo, hi = -1.0, 1.0
    qs = np.linspace(hi - 0.5, hi, 20001)
    b = jl.acc_bounds(
        jnp.asarray(np.stack([qs, np.zeros_like(qs)], -1), dtype),
        jnp.asarray([[v1, 0.0]], dtype),
        d.limits,
        d.dt,
        integrator="semi_implicit",
        substeps=5,
    )
    up = np.asarray(b.upper[:, 0], float)
    i = int(np.argmax(up <= -A_MAX[0] + 1e-3))
    assert -A_MAX[0] <= up[i] <= -A_MAX[0] + 1e-3 and lo < qs[i] < hi
    return jnp.asarray([qs[i], 0.0], dtype), jnp.asarray([v1, 0.0], dtype)


@pytest.mark.parametrize("x64", [False, True])
def test_without_torque_limits_the_decision_is_the_clip_and_jit_agrees(decide, x64):
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        d = decide["viability"]
        q, v = jnp.asarray([0.9, -0.2], dtype), jnp.asarray([0.8, -1.0], dtype)
        a_des = jnp.asarray([5.0, -0.5], dtype)
        dec = d(q, v, a_des)
        b = jl.acc_bounds(q, v, d.limits, d.dt, integrator="semi_implicit", substeps=5)
        np.testing.assert_array_equal(dec.a_safe, jnp.clip(a_des, b.lower, b.upper))
        assert dec.a_safe.dtype == dtype and not bool(dec.conflict)
        jitted = jax.jit(lambda q, v, a: d(q, v, a).a_safe)(q, v, a_des)
        np.testing.assert_allclose(jitted, dec.a_safe, rtol=1e-6)
        assert float(SafeAcceleration.beyond_bounds(dec)) == 0.0


@pytest.mark.parametrize("x64", [False, True])
def test_a_realisable_clip_is_kept_exactly(decide, x64):
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        d = decide["viability"]
        q, v = jnp.asarray([0.2, -0.3], dtype), jnp.asarray([0.5, 0.1], dtype)
        M = np.array([[0.5, 0.1], [0.1, 0.2]])
        f = np.array([-1.0, 0.3])
        torque = _torque(dtype, M, f, [-10, -10], [10, 10])
        dec = d(q, v, jnp.asarray([9.0, -9.0], dtype), None, torque)
        b = jl.acc_bounds(q, v, d.limits, d.dt, integrator="semi_implicit", substeps=5)
        np.testing.assert_allclose(dec.a_safe, np.clip([9.0, -9.0], b.lower, b.upper), atol=1e-6)
        assert not bool(dec.conflict) and float(SafeAcceleration.beyond_bounds(dec)) == 0.0


@pytest.mark.parametrize("method", ["viability", "jerk"])
@pytest.mark.parametrize("x64", [False, True])
def test_gravity_braking_harder_than_a_max_gives_way_on_the_acceleration_limit_only(decide, method, x64):
    """Joint 1's bounds are pinched at ``-a_max``, and the actuator cannot hold back gravity (its largest
    torque leaves ``a < -a_max``): no acceleration inside the bounds is realisable. The decision is then the
    realisable one nearest to the clip, below ``-a_max`` on joint 1 (braking harder: safe), inside the
    position/velocity/viability terms, with joint 2's command kept; not a conflict, and measured."""
    with jax.enable_x64(x64):
        dtype = jnp.float64 if x64 else jnp.float32
        d = decide[method]
        q, v = _pinched_state(decide, dtype)
        M = np.diag([0.5, 0.2])
        f = np.array([-3.0, 0.0])  # gravity: a = (tau + f) / M, joint 1 falls at -6 rad/s^2 with no torque
        tau_lo, tau_hi = np.array([-1.0, -5.0]), np.array([1.0, 5.0])  # joint 1: a in [-8, -4]
        torque = _torque(dtype, M, f, tau_lo, tau_hi)
        a_prev = jnp.asarray([-A_MAX[0], 0.0], dtype)
        dec = d(q, v, jnp.asarray([0.0, 0.7], dtype), a_prev, torque)
        a = np.asarray(dec.a_safe, float)
        tau = M @ a - f
        tol = 1e-5 if x64 else 1e-3
        assert np.all(tau >= tau_lo - tol) and np.all(tau <= tau_hi + tol), tau
        np.testing.assert_allclose(a, [-4.0, 0.7], atol=tol)  # the nearest realisable: joint 1 at tau_hi
        assert not bool(dec.conflict)
        np.testing.assert_allclose(float(SafeAcceleration.beyond_bounds(dec)), 4.0 - A_MAX[0], atol=tol)
        # the position and velocity limits hold over the step at that acceleration (semi-implicit substeps)
        h = d.dt / 5
        qq, vv = np.asarray(q, float), np.asarray(v, float)
        for _ in range(5):
            vv = vv + h * a
            qq = qq + h * vv
            assert np.all(qq <= 1.0) and np.all(np.abs(vv) <= 1.5)


def test_nan_command_brakes_and_is_flagged(decide):
    d = decide["viability"]
    q, v = jnp.asarray([0.0, 0.0], jnp.float32), jnp.asarray([1.0, -1.0], jnp.float32)
    torque = _torque(jnp.float32, np.eye(2), np.zeros(2), [-10, -10], [10, 10])
    for t in (None, torque):
        dec = d(q, v, jnp.asarray([jnp.nan, 0.0], jnp.float32), None, t)
        assert bool(dec.nonfinite) and np.all(np.isfinite(dec.a_safe))
        np.testing.assert_allclose(dec.a_safe, -np.sign([1.0, -1.0]) * A_MAX, rtol=1e-5)


def test_acceleration_space_first_solve_equals_the_torque_space_one(decide, monkeypatch, x64):
    """The first solve is written in the acceleration (box: the bounds, rows: the torque limits) for speed;
    it is the same problem as the torque-space one (same feasible set, same Gauss metric), so on random
    states, commands and torque models (feasible, infeasible, gravity-loaded) the decision is the same."""
    from jaxlimits.envs import joint_shield

    d = decide["viability"]
    r = np.random.default_rng(7)
    N = 400
    q, v = r.uniform(-1.0, 1.0, (N, 2)), r.uniform(-1.5, 1.5, (N, 2))
    A = r.normal(size=(N, 2, 2))
    M = A @ np.swapaxes(A, -1, -2) + 0.2 * np.eye(2)
    f, tau_hi = r.normal(scale=3.0, size=(N, 2)), r.uniform(0.5, 6.0, (N, 2))
    a_des = r.uniform(-8.0, 8.0, (N, 2))

    def one(q, v, a, M, f, hi):
        dec = d(q, v, a, None, TorqueModel(M, f, -hi, hi))
        return dec.a_safe, dec.conflict, SafeAcceleration.beyond_bounds(dec)

    out = {}
    for accel_first in (True, False):
        monkeypatch.setattr(joint_shield, "ACCEL_SPACE_FIRST", accel_first)
        out[accel_first] = [np.asarray(x) for x in jax.jit(jax.vmap(one))(q, v, a_des, M, f, tau_hi)]
    np.testing.assert_allclose(out[True][0], out[False][0], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(out[True][1], out[False][1])
    gave_way = int(np.sum(out[True][2] > 0))
    assert 0 < gave_way < N  # both branches of the decision are covered


def test_a_solve_that_did_not_converge_is_not_used(decide, monkeypatch):
    """A first (acceleration-space) solve that reports ``converged=False`` gives way to the second solve, as an
    infeasible one does; before, only ``infeasible`` and non-finite answers did, and a not-converged iterate far
    outside the torque rows was clipped into the bounds and used (a UR5e decision: 72 N m past its elbow's
    torque limit, then a velocity overshoot; ``tests/test_qp.py`` has that problem)."""
    from jaxlimits.envs import joint_shield

    d = decide["viability"]
    q, v = jnp.asarray([0.0, 0.0], jnp.float32), jnp.asarray([0.2, -0.1], jnp.float32)
    torque = _torque(jnp.float32, np.eye(2), np.zeros(2), [-10.0, -10.0], [10.0, 10.0])
    a_des = jnp.asarray([0.3, -0.7], jnp.float32)  # inside the bounds and realisable: the answer is a_des
    calls = []
    real = jl.solve_box_qp

    def first_not_converged(*args, **kwargs):
        res = real(*args, **kwargs)
        calls.append(len(calls))
        if len(calls) == 1:  # the acceleration-space solve: a far, not-converged iterate (inside the box)
            return res._replace(x=jnp.broadcast_to(args[2], res.x.shape), converged=jnp.zeros_like(res.converged))
        return res

    monkeypatch.setattr(joint_shield.jl, "solve_box_qp", first_not_converged)
    dec = d(q, v, a_des, None, torque)
    assert len(calls) == 2  # the second solve ran
    np.testing.assert_allclose(np.asarray(dec.a_safe), np.asarray(a_des), atol=1e-5)
    assert not bool(dec.conflict)
