"""Composition of limits (``jl.intersect``) and the dynamics-fed families (``jl.TorqueBox``, ``jl.ImpactCap``)."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlimits as jl
import jaxlimits.impact as jli


def box(lower, upper, viable=True):
    lower = jnp.asarray(lower)
    return jl.Bounds(lower, jnp.asarray(upper), jnp.full(lower.shape, viable))


def test_intersection_and_conflict_rule():
    limits = box([-5.0, 2.0, -9.0, -3.0], [5.0, 6.0, -4.0, 1.0])
    torque = box([-2.0, -1.0, -3.0, -0.5], [2.0, 1.0, 3.0, 0.5])
    out = jl.intersect(limits, torque)
    # joints 0 and 3: overlap -> intersection; joint 1: limits need a >= 2 > box -> keep lower (2);
    # joint 2: limits need a <= -4 < box -> keep upper (-4): the limits' braking side, never the box
    np.testing.assert_array_equal(out.conflict, [False, True, True, False])
    np.testing.assert_array_equal(out.bounds.lower, [-2.0, 2.0, -4.0, -0.5])
    np.testing.assert_array_equal(out.bounds.upper, [2.0, 2.0, -4.0, 0.5])
    assert out.G is None and out.h is None


def test_priority_order_and_viable_conjunction():
    a = box([0.0, -1.0], [1.0, 1.0])
    b = box([2.0, -0.5], [3.0, 0.5], viable=False)
    c = box([-3.0, 0.2], [-2.0, 0.4])
    out = jl.intersect(a, b, c)
    # joint 0: a and b disjoint -> a's end nearest b (1.0); then c disjoint from {1} -> stays 1.0
    # joint 1: a ∩ b = [-0.5, 0.5], ∩ c = [0.2, 0.4]
    np.testing.assert_array_equal(out.bounds.lower, np.float32([1.0, 0.2]))
    np.testing.assert_array_equal(out.bounds.upper, np.float32([1.0, 0.4]))
    np.testing.assert_array_equal(out.conflict, [True, False])
    np.testing.assert_array_equal(out.bounds.viable, [False, False])
    # the order matters: c first keeps c's end nearest the rest
    np.testing.assert_array_equal(jl.intersect(c, a, b).bounds.upper, np.float32([-2.0, 0.4]))


def test_intersect_is_jittable_and_broadcasts():
    lim = jl.JointLimits(-1.0, 1.0, 2.0, 10.0)
    q = jnp.linspace(-0.9, 0.9, 12).reshape(4, 3)
    v = jnp.full((4, 3), 1.5)

    def f(q, v):
        b = jl.acc_bounds(q, v, lim, 0.01)
        return jl.intersect(b, box(jnp.full(3, -4.0), jnp.full(3, 4.0)))

    eager, jitted = f(q, v), jax.jit(f)(q, v)
    np.testing.assert_allclose(eager.bounds.upper, jitted.bounds.upper, rtol=0, atol=1e-6)
    assert eager.bounds.lower.shape == (4, 3) and eager.conflict.shape == (4, 3)
    assert np.all(np.asarray(eager.bounds.lower) <= np.asarray(eager.bounds.upper))
    assert np.all(np.asarray(eager.bounds.upper) <= 4.0)


def _spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def test_torque_box_every_vertex_is_realisable(x64):
    rng = np.random.default_rng(0)
    n = 4
    a_nom = np.array([10.0, 8.0, 12.0, 6.0])
    tau = np.array([80.0, 80.0, 40.0, 30.0])
    for _ in range(20):
        M, h = _spd(rng, n), rng.normal(scale=5.0, size=n)
        limit = jl.TorqueBox(M, h, tau, a_nom)
        b = limit.bounds(None, None)
        assert np.all(np.asarray(b.viable)) == (float(limit.scale()) > 0)
        for signs in itertools.product((-1.0, 1.0), repeat=n):
            a = np.where(np.array(signs) > 0, b.upper, b.lower)
            assert np.all(np.abs(M @ a + h) <= tau * (1 + 1e-12))
        if 0 < float(limit.scale()) < 1:  # tight: a slightly larger box has a vertex beyond some torque limit
            big = 1.001 * np.asarray(b.upper)
            worst = max(np.max(np.abs(M @ (np.array(s) * big) + h) - tau) for s in itertools.product((-1, 1), repeat=n))
            assert worst > 0
    # gravity alone beyond a torque limit: the box collapses to {0} and is not viable
    b = jl.TorqueBox(np.eye(n), np.array([100.0, 0, 0, 0]), tau, a_nom).bounds(None, None)
    np.testing.assert_array_equal(b.lower, 0.0)
    np.testing.assert_array_equal(b.upper, 0.0)
    assert not np.any(np.asarray(b.viable))


def test_impact_cap_is_a_row_never_dropped(x64):
    rng = np.random.default_rng(1)
    n = 3
    M, J = _spd(rng, n), rng.normal(size=(3, n))
    normal = np.array([0.0, 0.0, 1.0])
    lim = jl.JointLimits(-2.0, 2.0, 2.0, 10.0)
    q, v = np.zeros(n), 0.1 * rng.normal(size=n)
    cap = jl.ImpactCap(M, J, normal, lim, 50.0, 0.01, 0.2, 0.002)
    with pytest.raises(TypeError, match="halfspace"):
        cap.bounds(q, v)
    c = cap.constraint(q, v)
    assert np.all(np.isinf(np.asarray(c.bounds.upper))) and np.all(np.isinf(np.asarray(c.bounds.lower)))
    ref_cap = jli.impact_speed_cap(M, J, normal, q, v, lim, 50.0, 0.01, 0.2, 0.002).cap
    G, h = jli.speed_cap_halfspace(M, J, normal, v, ref_cap, 0.01)
    np.testing.assert_allclose(c.G, G)
    np.testing.assert_allclose(c.h, h)
    assert np.all(np.asarray(c.bounds.viable)) == (float(ref_cap) > 0)
    # composed with the viability bounds: the box is theirs, the row is kept
    b = jl.acc_bounds(q, v, lim, 0.01)
    out = jl.intersect(b, c)
    np.testing.assert_array_equal(out.bounds.lower, b.lower)
    np.testing.assert_array_equal(out.bounds.upper, b.upper)
    assert out.G.shape == (1, n) and out.h.shape == (1,)
    # projecting onto box and row gives a command whose end-of-step approach speed is within the cap
    a_des = np.asarray(b.upper)
    res = jl.solve_box_qp(a_des, out.bounds.lower, out.bounds.upper, G=out.G, h=out.h)
    w = normal @ J @ (v + 0.01 * np.asarray(res.x))
    assert w <= float(ref_cap) + 1e-9 or bool(res.infeasible)
    with pytest.raises(ValueError, match="margin"):
        jl.ImpactCap(M, J, normal, lim, 50.0, 0.01, 0.2, 0.002, margin=1.5)


def test_intersect_rejects_other_types():
    with pytest.raises(TypeError, match="Bounds or Constraint"):
        jl.intersect((np.zeros(2), np.ones(2), np.ones(2, bool)))
