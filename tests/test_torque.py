"""Torque limits -> acceleration limits (Del Prete 2018, Alg. 4): core on an analytic model, MJX vs C."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlimits.envs  # noqa: F401  (sets the XLA CPU flags; must come before any JAX computation)
from jaxlimits._src import torque

TAU = np.array([30.0, 8.0])


def two_link(q, v):
    """Planar 2-link arm, point masses at the link ends, unit lengths (textbook M and h)."""
    m1, m2, g = 1.0, 0.5, 9.81
    c2, s2 = jnp.cos(q[1]), jnp.sin(q[1])
    M = jnp.array([[m1 + 2 * m2 + 2 * m2 * c2, m2 + m2 * c2], [m2 + m2 * c2, m2 + 0 * c2]])
    h = jnp.array(
        [
            -m2 * s2 * (2 * v[0] * v[1] + v[1] ** 2) + (m1 + m2) * g * jnp.cos(q[0]) + m2 * g * jnp.cos(q[0] + q[1]),
            m2 * s2 * v[0] ** 2 + m2 * g * jnp.cos(q[0] + q[1]),
        ]
    )
    return M, h


def test_alg4_is_the_worst_case_of_the_per_state_box():
    key = jax.random.PRNGKey(0)
    q_min, q_max, v_max = np.array([-1.0, -2.0]), np.array([1.0, 2.0]), np.array([1.0, 1.5])
    b = torque.acc_bounds_from_torque(two_link, q_min, q_max, v_max, TAU, 5000, key, a_nominal=[1.0, 1.0], chunk=1024)
    q, v = torque.sample_states(key, q_min, q_max, v_max, 5000)
    M, h = jax.vmap(two_link)(q, v)
    lo, hi = torque.torque_acc_box(M, h, TAU)
    np.testing.assert_allclose(b.lower, lo.max(0), rtol=1e-6)
    np.testing.assert_allclose(b.upper, hi.min(0), rtol=1e-6)
    np.testing.assert_allclose(b.scale, torque.box_scale(M, h, TAU, [1.0, 1.0]).min(), rtol=1e-6)
    # same answer through the padded last chunk
    b2 = torque.acc_bounds_from_torque(two_link, q_min, q_max, v_max, TAU, 5000, key, a_nominal=[1.0, 1.0], chunk=4096)
    np.testing.assert_allclose(b2.lower, b.lower, rtol=1e-6)


def test_per_state_box_is_exact_for_one_joint():
    M, h = two_link(jnp.array([0.3, -0.7]), jnp.array([0.5, -1.0]))
    lo, hi = torque.torque_acc_box(M, h, TAU)
    for j in range(2):
        for a_j, sign in ((lo[j], -1.0), (hi[j], 1.0)):
            a = jnp.zeros(2).at[j].set(a_j)
            np.testing.assert_allclose((M @ a + h)[j], sign * TAU[j], rtol=1e-5)


def test_conservative_box_is_realisable_at_its_vertices_and_tight():
    rng = np.random.default_rng(0)
    a_nom = np.array([3.0, 4.0])
    for _ in range(50):
        q, v = rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2)
        M, h = two_link(jnp.asarray(q, jnp.float32), jnp.asarray(v, jnp.float32))
        s = float(torque.box_scale(M, h, TAU, a_nom))
        lo, hi = torque.torque_acc_box_conservative(M, h, TAU, a_nom)
        torques = [
            np.abs(np.asarray(M) @ np.array([x, y]) + np.asarray(h)) for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
        ]
        assert np.all(np.max(torques, axis=0) <= TAU * (1 + 1e-5))
        assert s > 0
        if s < 1:  # some vertex saturates some joint exactly
            assert np.max(np.array(torques) / TAU) == pytest.approx(1.0, rel=1e-4)


@pytest.fixture(scope="module")
def planar():
    from jaxlimits.envs.arm import make_planar_reach

    return make_planar_reach()


def test_mjx_alg4_matches_mujoco_c(planar):
    """Alg. 4 over MJX dynamics == the same reduction over MuJoCo's C ``mj_fullM``/``mj_rne``."""
    from jaxlimits.envs.arm import dynamics_c, sample_states

    lim = planar.limits
    q, v = sample_states(np.random.default_rng(1), lim.q_min, lim.q_max, lim.v_max, 256)
    M_c, h_c = dynamics_c(planar.mj_model, q, v)
    b = torque.acc_bounds_from_torque(
        planar.mass_and_bias,
        lim.q_min,
        lim.q_max,
        lim.v_max,
        planar.tau_max,
        256,
        None,
        a_nominal=planar.a_max_nominal,
        states=(q, v),
        chunk=64,
    )
    lo, hi = torque.torque_acc_box(M_c, h_c, planar.tau_max)
    np.testing.assert_allclose(b.lower, lo.max(0), rtol=1e-4)
    np.testing.assert_allclose(b.upper, hi.min(0), rtol=1e-4)
    s_c = torque.box_scale(M_c, h_c, planar.tau_max, planar.a_max_nominal, xp=np).min()
    np.testing.assert_allclose(b.scale, s_c, rtol=1e-4)


def test_panda_a_max_is_torque_derived():
    """The Panda's datasheet accelerations need more torque than its motors have at some states."""
    from jaxlimits.envs.arm import make_panda_reach

    panda = make_panda_reach()
    assert 0.0 < panda.torque_scale < 1.0
    np.testing.assert_allclose(panda.limits.a_max, 0.8 * panda.torque_scale * panda.a_max_nominal)
