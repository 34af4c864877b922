"""The semi-implicit model's closed forms against brute force over every integer (float64, float32).

``SemiImplicit.position_upper`` evaluates ``min_{k=1..n} (d - k h v) / c_k`` at one ``k`` given in
closed form (``substep_argmin``: ``f(k+1) <= f(k)`` iff ``k h v <= 2 d``), ``viability_upper`` the
minimum over ``K >= 0`` of the line roots ``x_K`` at one active ``K`` (``braking_piece``) and
``braking_distance`` the maximum of three lines around ``floor(v / (a_max h))``. Here each is
compared with the minimum (maximum) over *all* integers, computed in numpy float64, on random
states and on the ties and kinks where a rounded selection could go wrong (``2 d = j h v``,
``R = P(K)``, ``v = K a_max h``), for substep counts 1 to 20. Derivation: docs/derivations.md §3.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits._src.semi_implicit import SemiImplicit, braking_piece, substep_argmin

SUBSTEPS = [1, 2, 3, 5, 7, 10, 20]
T = 0.01
A_MAX = 12.0
K_ALL = 4000  # more lines than any state below needs (K <= v / (a_max h) <= 6 / (12 * 0.0005) = 1000)


def _states(rng, n, m=3000):
    """``(d, v)`` float64: random, ties ``2 d = j h v`` (and one ulp off), rest, past the limit."""
    h = T / n
    d = rng.uniform(-0.5, 2.0, m) * 10.0 ** rng.uniform(-6, 0, m)
    v = rng.uniform(-6.0, 6.0, m) * 10.0 ** rng.uniform(-4, 0, m)
    j = rng.integers(1, n + 1, m).astype(float)
    v_tie = np.abs(v)
    d_tie = j * h * v_tie / 2.0
    d_ulp = np.nextafter(d_tie, np.where(rng.random(m) < 0.5, np.inf, -np.inf))
    zeros = np.zeros(8)
    special_d = np.array([0.0, 0.0, 0.0, -1e-3, -1e-3, 1e-3, 1e-300, -1e-300])
    special_v = np.array([0.0, 1.0, -1.0, 1e-3, -1e-3, 0.0, 1e-300, -1e-300])
    return (
        np.concatenate([d, d_tie, d_ulp, special_d, zeros + 1.0]),
        np.concatenate([v, v_tie, v_tie, special_v, zeros - 1e-9]),
    )


def brute_position_upper(d, v, n):
    h = T / n
    k = np.arange(1, n + 1, dtype=float)
    f = (d[:, None] - k * h * v[:, None]) / (h * h * k * (k + 1.0) / 2.0)
    return f.min(axis=1), f


def brute_viability_upper(d, v, n):
    h = T / n
    R = d - h * (n - 1) * v / 2.0
    K = np.arange(0, K_ALL, dtype=float)
    x = (2.0 * R[:, None] / h + A_MAX * h * K * (K + 1.0)) / (n + 1.0 + 2.0 * K)
    return (x.min(axis=1) - v) / T


def brute_braking_distance(v, n):
    """``h sum_{k>=1} max(v - k h a_max, 0)``, the definition (no closed form)."""
    h = T / n
    k = np.arange(1, K_ALL, dtype=float)
    return h * np.maximum(v[:, None] - k * h * A_MAX, 0.0).sum(axis=1)


@pytest.mark.parametrize("n", SUBSTEPS)
def test_position_upper_is_the_min_over_every_substep(n, x64):
    d, v = _states(np.random.default_rng(n), n)
    want, f = brute_position_upper(d, v, n)
    model = SemiImplicit(T, n)
    got = np.asarray(jax.jit(model.position_upper)(jnp.asarray(d), jnp.asarray(v), jnp.full(d.shape, A_MAX)))
    scale = np.abs(f).max(axis=1) + 1.0
    assert np.all(np.abs(got - want) <= 1e-13 * scale), np.max(np.abs(got - want) / scale)
    # the chosen k is a true minimiser wherever the minimum is not a tie (up to rounding)
    k = np.asarray(substep_argmin(jnp.asarray(d), jnp.asarray(T / n * v), n))
    assert np.all((k >= 1) & (k <= n) & (k == np.round(k)))
    f_at_k = np.take_along_axis(f, (k.astype(int) - 1)[:, None], axis=1)[:, 0]
    assert np.all(f_at_k - want <= 1e-13 * scale)


@pytest.mark.parametrize("n", SUBSTEPS)
def test_position_upper_float32_within_rounding_of_the_float64_min(n):
    d, v = _states(np.random.default_rng(100 + n), n)
    d32, v32 = d.astype(np.float32), v.astype(np.float32)
    want, f = brute_position_upper(d32.astype(float), v32.astype(float), n)
    got = np.asarray(jax.jit(SemiImplicit(T, n).position_upper)(d32, v32, np.full(d.shape, A_MAX, np.float32)))
    assert got.dtype == np.float32
    scale = np.abs(f).max(axis=1) + 1.0
    assert np.all(np.abs(got - want) <= 1e-5 * scale), np.max(np.abs(got - want) / scale)


@pytest.mark.parametrize("n", SUBSTEPS)
def test_viability_upper_is_the_min_over_every_braking_piece(n, x64):
    d, v = _states(np.random.default_rng(200 + n), n)
    d, v = np.clip(d, -4.0, 8.0), np.clip(v, -6.0, 6.0)
    want = brute_viability_upper(d, v, n)
    got = np.asarray(
        jax.jit(SemiImplicit(T, n).viability_upper)(jnp.asarray(d), jnp.asarray(v), jnp.full(d.shape, A_MAX))
    )
    scale = np.abs(want) + A_MAX
    assert np.all(np.abs(got - want) <= 1e-12 * scale), np.max(np.abs(got - want) / scale)
    # the root solves the definition: q_n + D(v_n) = q_max, D by direct summation
    h = T / n
    x = v + T * got
    lhs = h * ((n - 1) * v + (n + 1) * x) / 2.0 + brute_braking_distance(x, n)
    assert np.all(np.abs(lhs - d) <= 1e-12 * (np.abs(d) + 1.0))


@pytest.mark.parametrize("n", SUBSTEPS)
def test_braking_piece_at_kinks_is_the_active_piece(n, x64):
    """``R = P(K)`` exactly and one ulp either side: ``K`` is the largest with ``P(K) <= R``."""
    h = T / n
    K = np.arange(0, 300, dtype=float)
    P = A_MAX * h * h * K * (K + n) / 2.0
    R = np.concatenate([P, np.nextafter(P, np.inf), np.nextafter(P, -np.inf), [-1.0, -1e-300]])
    got = np.asarray(braking_piece(jnp.asarray(R), jnp.full(R.shape, A_MAX), h, n))
    Kall = np.arange(0, 400, dtype=float)
    Pall = A_MAX * h * h * Kall * (Kall + n) / 2.0
    want = np.maximum((Pall[None, :] <= R[:, None]).sum(axis=1) - 1.0, 0.0)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("n", SUBSTEPS)
def test_braking_distance_is_the_sum_of_the_braking_velocities(n, dtype):
    h = T / n
    rng = np.random.default_rng(300 + n)
    kinks = np.arange(0, 50) * A_MAX * h
    v = np.concatenate([rng.uniform(-1.0, 6.0, 2000), kinks, np.nextafter(kinks, np.inf), np.nextafter(kinks, -np.inf)])
    v = v.astype(dtype)
    got = np.asarray(jax.jit(SemiImplicit(T, n).braking_distance)(v, np.full(v.shape, A_MAX, dtype)))
    want = brute_braking_distance(v.astype(float), n)
    tol = (1e-13 if dtype == np.float64 else 2e-6) * (want + 1e-3)
    assert np.all(np.abs(got - want) <= tol), np.max(np.abs(got - want) / (want + 1e-3))


@pytest.mark.parametrize("n", [1, 5, 10])
@pytest.mark.parametrize("method", ["position_upper", "viability_upper"])
def test_gradients_finite_on_ties_kinks_and_limits(n, method, dtype):
    """On ``2 d = j h v``, the kinks of ``D``, ``d = 0`` and ``v = 0`` the derivative is a piece's (finite)."""
    h = T / n
    v = np.array([0.0, 0.0, 1.0, -1.0, 2.0, 2.0, 1e-30, 3.0], dtype)
    d = np.array(
        [0.0, 0.1, 0.0, 0.0, 2.0 * h * 2.0 / 2.0, 0.0, 0.0, A_MAX * h * h * 4 * (4 + n) / 2.0 + h * (n - 1) * 1.5],
        dtype,
    )
    fn = getattr(SemiImplicit(T, n), method)
    a = np.full(d.shape, A_MAX, dtype)
    val = fn(jnp.asarray(d), jnp.asarray(v), jnp.asarray(a))
    gd, gv = jax.grad(lambda d, v: jnp.sum(fn(d, v, jnp.asarray(a))), argnums=(0, 1))(jnp.asarray(d), jnp.asarray(v))
    assert val.dtype == dtype and gd.dtype == dtype
    assert np.all(np.isfinite(val)) and np.all(np.isfinite(gd)) and np.all(np.isfinite(gv))
    assert np.all(np.asarray(gd) > 0)  # more room always allows more acceleration


def test_elementwise_and_broadcasting():
    model = SemiImplicit(T, 5)
    d = jnp.linspace(-0.1, 1.0, 12).reshape(3, 4)
    v = jnp.linspace(-2.0, 2.0, 4)[None, :]  # same rank (the suite raises on rank promotion)
    a = jnp.full((1, 4), A_MAX)
    for fn in (model.position_upper, model.viability_upper):
        out = fn(d, v, a)
        assert out.shape == (3, 4)
        np.testing.assert_array_equal(np.asarray(out)[1], np.asarray(fn(d[1:2], v, a))[0])
    assert model.braking_distance(v, a).shape == (1, 4)
