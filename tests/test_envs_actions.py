"""Action modes before the shield, the IK observation, and gradients through the shielded step (APG's path)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.envs.actions import VelocityActions, velocity_to_acc, with_action_mode
from jaxlimits.envs.arm import make_planar_reach
from jaxlimits.envs.safety import SafetyWrapper


@pytest.fixture(scope="module")
def env():
    return make_planar_reach(ik_observation=True)


def test_velocity_mode_tracks_deadbeat_and_keeps_the_guarantee(env):
    """First step: a reachable ``v_des`` is met at the end of the step (semi-implicit model, f32
    roundoff), untouched by the shield. Then always asking for +v_max (or -v_max) drives every joint
    to its limit: zero violations, arrival at rest on the limit. One compiled rollout."""
    w = VelocityActions(SafetyWrapper(env, "viability"))
    gentle = jnp.asarray([0.002, -0.004, 0.001])  # v_des = gentle * v_max: |v_des - v| / dt < a_max

    @jax.jit
    def run(key, sign):
        s = w.reset(key)
        s = s.replace(pipeline_state=s.pipeline_state.replace(qvel=jnp.asarray([0.01, -0.02, 0.0], jnp.float32)))

        def body(s, t):
            s = w.step(s, jnp.where(t == 0, gentle, sign * jnp.ones(3)))
            m = s.metrics
            return s, (m["count/position"], m["count/velocity"], m["intervention"], s.pipeline_state.qvel)

        return jax.lax.scan(body, s, jnp.arange(250))

    for sign in (1.0, -1.0):
        s, (pos, vel, intervention, qvel) = run(jax.random.PRNGKey(3), sign)
        np.testing.assert_allclose(qvel[0], gentle * env.limits.v_max, atol=2e-5)
        assert float(intervention[0]) == 0.0
        assert float(pos.sum()) == 0 and float(vel.sum()) == 0
        q = np.asarray(s.pipeline_state.qpos)
        limit = env.limits.q_max if sign > 0 else env.limits.q_min
        np.testing.assert_allclose(q, limit, atol=2e-3)


def test_velocity_to_acc_and_mode_errors():
    np.testing.assert_allclose(velocity_to_acc(jnp.ones(2), jnp.zeros(2), 0.01), 100.0 * np.ones(2))
    assert not np.all(np.isfinite(velocity_to_acc(jnp.asarray([np.nan, 0.0]), jnp.zeros(2), 0.01)))
    with pytest.raises(ValueError, match="action mode"):
        with_action_mode(None, "torque")
    from jaxlimits.envs.task_space import TaskSpaceActions

    assert isinstance(
        with_action_mode(SafetyWrapper(make_planar_reach(torque_samples=0)), "task_space"), TaskSpaceActions
    )


def test_ik_observation_is_the_damped_least_squares_step(env):
    """The appended entries equal ``J^T (J J^T + lam^2 I)^-1 e`` with ``J`` from finite differences of the FK."""
    from jaxlimits.envs.arm import IK_DAMPING

    s = jax.jit(env.reset)(jax.random.PRNGKey(5))  # jitted: MJX op by op takes longer than its compile
    q = np.asarray(s.pipeline_state.qpos, np.float64)
    obs = np.asarray(s.obs)
    assert obs.shape == (env.observation_size,) == (4 * env.n + 6,)
    err = obs[3 * env.n + 3 : 3 * env.n + 6]
    eps = 1e-3
    steps = eps * np.eye(env.n)
    fk = np.asarray(jax.jit(jax.vmap(env.ee_position))(np.concatenate([q + steps, q - steps])), np.float64)
    J = (fk[: env.n] - fk[env.n :]).T / (2 * eps)
    expected = J.T @ np.linalg.solve(J @ J.T + IK_DAMPING**2 * np.eye(3), err)
    np.testing.assert_allclose(obs[4 * env.n + 6 - env.n :], expected, atol=2e-3 * max(1.0, np.abs(expected).max()))


def test_gradient_through_the_shield_is_the_projection_derivative(env):
    """APG differentiates the reward through the shielded step: a joint the bounds clip passes no gradient
    to its action (the clip's derivative), a free joint passes the physics' gradient (finite differences)."""
    w = SafetyWrapper(env, "viability")
    s = jax.jit(w.reset)(jax.random.PRNGKey(7))  # jitted: MJX op by op takes longer than its compile
    q = 0.5 * (env.limits.q_max + env.limits.q_min)
    q[0] = env.limits.q_max[0] - 0.18  # joint 0 fast toward its limit (stopping distance 0.162 rad): it must brake
    v = np.array([env.limits.v_max[0] * 0.9, 0.0, 0.0])
    s = s.replace(
        pipeline_state=s.pipeline_state.replace(qpos=jnp.asarray(q, jnp.float32), qvel=jnp.asarray(v, jnp.float32))
    )
    b = w.bounds(s)
    action = jnp.asarray([1.0, 0.3, -0.2], jnp.float32)  # joint 0 above its (braking) upper bound, others inside
    a_max = np.asarray(env.limits.a_max)
    assert float(action[0] * a_max[0]) > float(b.upper[0])
    assert np.all(
        (np.asarray(action[1:]) * a_max[1:] > np.asarray(b.lower[1:]))
        & (np.asarray(action[1:]) * a_max[1:] < np.asarray(b.upper[1:]))
    )

    def reward(a):
        return w.step(s, a).reward

    g = np.asarray(jax.jit(jax.grad(reward))(action))
    reward = jax.jit(reward)
    assert np.all(np.isfinite(g))
    assert g[0] == 0.0
    eps = 1e-2
    for j in (1, 2):
        e = np.zeros(3, np.float32)
        e[j] = eps
        fd = (float(reward(action + e)) - float(reward(action - e))) / (2 * eps)
        assert g[j] != 0.0
        np.testing.assert_allclose(g[j], fd, rtol=0.05, atol=1e-6)


def test_straight_through_shield_gradient_is_opt_in_and_keeps_the_value(env):
    """``SafetyWrapper(gradient="straight_through")``: the same safe command bit for bit, and the
    derivative of the shield w.r.t. the command is the identity (the exact one is 0 on a clipped
    joint, 1 on a free one). No physics step: the shield alone, at a state where joint 0 must brake."""
    exact, straight = SafetyWrapper(env, "viability"), SafetyWrapper(env, "viability", gradient="straight_through")
    s = exact.reset(jax.random.PRNGKey(3))
    q = 0.5 * (env.limits.q_max + env.limits.q_min)
    q[0] = env.limits.q_max[0] - 0.18
    v = np.array([env.limits.v_max[0] * 0.9, 0.0, 0.0])
    s = s.replace(
        pipeline_state=s.pipeline_state.replace(qpos=jnp.asarray(q, jnp.float32), qvel=jnp.asarray(v, jnp.float32))
    )
    a_des = jnp.asarray([1.0, 0.3, -0.2], jnp.float32) * jnp.asarray(env.limits.a_max, jnp.float32)
    b = exact.bounds(s)
    assert float(a_des[0]) > float(b.upper[0])  # joint 0 is clipped, the others are free
    a_exact, a_straight = exact.shield(s, a_des)[0], straight.shield(s, a_des)[0]
    np.testing.assert_array_equal(np.asarray(a_exact), np.asarray(a_straight))
    jac_exact = np.asarray(jax.jacobian(lambda a: exact.shield(s, a)[0])(a_des))
    jac_straight = np.asarray(jax.jacobian(lambda a: straight.shield(s, a)[0])(a_des))
    np.testing.assert_array_equal(jac_exact, np.diag([0.0, 1.0, 1.0]))
    np.testing.assert_array_equal(jac_straight, np.eye(3))
    # "exact_fixed_bounds": the same value and command derivative as "exact", but the clipped joint's safe
    # command no longer moves with the state through its bound (the exact one does: the braking bound)
    fixed = SafetyWrapper(env, "viability", gradient="exact_fixed_bounds")
    np.testing.assert_array_equal(np.asarray(fixed.shield(s, a_des)[0]), np.asarray(a_exact))
    np.testing.assert_array_equal(np.asarray(jax.jacobian(lambda a: fixed.shield(s, a)[0])(a_des)), jac_exact)

    def d_state(w):
        def out(v):
            return w.shield(s.replace(pipeline_state=s.pipeline_state.replace(qvel=v)), a_des)[0]

        return np.asarray(jax.jacobian(out)(s.pipeline_state.qvel))

    assert np.abs(d_state(exact)[0]).max() > 0.0 and np.all(d_state(fixed) == 0.0)
    with pytest.raises(ValueError, match="gradient"):
        SafetyWrapper(env, "viability", gradient="smooth")


@pytest.mark.parametrize("make", ["planar", "panda_wall"])
def test_analytic_ee_jacobian_equals_autodiff_of_the_kinematics(make):
    """``ee_jacobian(q)`` (MJX's analytic ``jac``) equals forward-mode autodiff of ``ee_position`` at random
    configurations (the arms compute in float32: to its rounding); ``ee_jacobian_at`` a state's ``pipeline_state`` equals ``ee_jacobian`` of its ``q`` (planar arm; the Panda wall's reset compiles its collisions)."""
    from jaxlimits.envs.wall_strike import make_wall_strike

    arm = make_planar_reach(torque_samples=0) if make == "planar" else make_wall_strike(torque_samples=0)
    lim = arm.limits
    rng = np.random.default_rng(0)
    qs = rng.uniform(lim.q_min, lim.q_max, (8, arm.n))
    J = np.asarray(jax.jit(jax.vmap(arm.ee_jacobian))(qs))  # jitted: MJX op by op takes longer than its compile
    J_ad = np.asarray(jax.jit(jax.vmap(jax.jacfwd(arm.ee_position)))(qs))
    assert J.shape == (8, 3, arm.n) and np.abs(J).max() > 0.1
    np.testing.assert_allclose(J, J_ad, atol=1e-6)
    if make != "planar":
        return
    s = jax.jit(arm.reset)(jax.random.PRNGKey(1))
    J_at, J_q = jax.jit(lambda s: (arm.ee_jacobian_at(s.pipeline_state), arm.ee_jacobian(s.pipeline_state.qpos)))(s)
    np.testing.assert_allclose(np.asarray(J_at), np.asarray(J_q), atol=1e-6)
