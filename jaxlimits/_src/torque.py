"""Torque limits -> acceleration limits (Del Prete 2018, Sec. IV, Alg. 4), simulator-free.

The rigid-body model is ``tau = M(q) a + h(q, v)`` (eq. 30). The caller passes either arrays
``M`` (..., n, n) and ``h`` (..., n) or a function ``dynamics(q, v) -> (M, h)`` for one state
(``jaxlimits.envs`` builds one from MJX; anything jittable and vmappable works), so this module
needs neither MuJoCo nor Pinocchio.

* ``torque_acc_box``: the per-state bounds of Alg. 4, lines 9-10: joint ``j`` alone may accelerate
  in ``[(-tau_j - h_j) / M_jj, (tau_j - h_j) / M_jj]`` when every other joint's acceleration is 0.
  Exact for one joint moving; not a guarantee when several do.
* ``box_scale`` / ``torque_acc_box_conservative``: the largest ``s`` such that *every*
  ``a`` in the box ``|a_j| <= s a_nom_j`` needs ``|M a + h| <= tau_max`` at this state:
  ``s = min_i (tau_i - |h_i|) / (|M| a_nom)_i`` (row ``i`` of ``M a`` is at most ``(|M| a_nom)_i s``).
  Exact for boxes of this shape; ``s <= 0`` means gravity/Coriolis alone exceed a torque limit.
* ``acc_bounds_from_torque``: Alg. 4 — sample ``N`` states uniformly in the position and velocity
  box and return the worst case over them of ``torque_acc_box`` (and, as ``scale``, of
  ``box_scale``). Sampling gives no guarantee between samples; half the velocity samples sit on
  the box's vertices, where the quadratic bias forces peak.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp


def _lead(x, ndim, xp=jnp):
    """``x`` with leading unit axes up to ``ndim`` dimensions (explicit broadcasting: rank promotion may raise)."""
    return xp.reshape(x, (1,) * (ndim - x.ndim) + tuple(x.shape))


class TorqueBounds(NamedTuple):
    """Worst-case acceleration bounds from torque limits.

    lower, upper: ``(n,)`` [rad/s^2], Alg. 4 (other joints' accelerations zero).
    scale: ``()``, the worst-case ``box_scale`` for ``a_nominal`` (``inf`` when none was given).
    """

    lower: jax.Array
    upper: jax.Array
    scale: jax.Array


def torque_acc_box(M, h, tau_max):
    """Per-state acceleration box of Alg. 4 (lines 9-10). ``M`` (..., n, n), ``h`` (..., n) -> (lower, upper)."""
    M, h = jnp.asarray(M), jnp.asarray(h)
    tau = _lead(jnp.asarray(tau_max, h.dtype), h.ndim)
    diag = jnp.diagonal(M, axis1=-2, axis2=-1)
    return (-tau - h) / diag, (tau - h) / diag


def box_scale(M, h, tau_max, a_nominal, xp=jnp):
    """Largest ``s`` with ``|M a + h| <= tau_max`` for all ``|a| <= s a_nominal`` (per state, shape ``(...)``).

    ``xp`` is the array module (``jnp`` or ``numpy``), so the same formula serves the C reference.
    """
    M, h = xp.asarray(M), xp.asarray(h)
    tau = _lead(xp.asarray(tau_max, dtype=h.dtype), h.ndim, xp)
    a_nom = _lead(xp.asarray(a_nominal, dtype=h.dtype), M.ndim, xp)
    reach = xp.sum(xp.abs(M) * a_nom, axis=-1)
    return xp.min((tau - xp.abs(h)) / reach, axis=-1)


def torque_acc_box_conservative(M, h, tau_max, a_nominal):
    """``(-s a_nominal, s a_nominal)`` with ``s = clip(box_scale, 0, 1)``: every ``a`` inside is realisable."""
    s = jnp.clip(box_scale(M, h, tau_max, a_nominal), 0.0, 1.0)[..., None]
    a_nom = _lead(jnp.asarray(a_nominal, s.dtype), s.ndim)
    return -s * a_nom, s * a_nom


def sample_states(key, q_min, q_max, v_max, n_samples: int, dtype=jnp.float32):
    """``n_samples`` states: uniform positions; velocities uniform (first half) or box vertices (second half)."""
    q_min, q_max, v_max = (jnp.asarray(x, dtype) for x in (q_min, q_max, v_max))
    n = q_min.shape[-1]
    kq, kv = jax.random.split(key)
    q = jax.random.uniform(kq, (n_samples, n), dtype, q_min[None], q_max[None])
    u = jax.random.uniform(kv, (n_samples, n), dtype, -1.0, 1.0)
    vertex = jnp.broadcast_to((jnp.arange(n_samples) >= n_samples // 2)[:, None], (n_samples, n))
    return q, jnp.where(vertex, jnp.sign(u), u) * v_max[None]


def acc_bounds_from_torque(
    dynamics: Callable,
    q_min,
    q_max,
    v_max,
    tau_max,
    n_samples: int,
    key,
    a_nominal=None,
    chunk: int = 8192,
    states=None,
) -> TorqueBounds:
    """Alg. 4 of Del Prete 2018: worst-case acceleration bounds over ``n_samples`` random states.

    Args:
      dynamics: ``(q, v) -> (M, h)`` for one state (``(n,)`` -> ``(n, n)``, ``(n,)``), jittable and
        vmappable.
      q_min, q_max, v_max, tau_max: ``(n,)`` limits [rad, rad/s, N m].
      n_samples: ``N``; processed in vmapped chunks of ``chunk`` under one ``lax.scan``.
      key: PRNG key for ``sample_states``.
      a_nominal: ``(n,)``; when given, ``scale`` is the worst-case ``box_scale`` (the torque-derived
        ``a_max`` is ``min(1, scale) * a_nominal``).
      states: optional ``(q, v)`` arrays ``(N, n)`` to use instead of sampling.

    Returns ``TorqueBounds(lower, upper, scale)``: ``lower = max_samples`` of the per-state lower
    bound and ``upper = min_samples`` of the upper one (Alg. 4, lines 11-12).
    """
    tau = jnp.asarray(tau_max, jnp.float32)
    if states is None:
        q, v = sample_states(key, q_min, q_max, v_max, n_samples)
    else:
        q, v = (jnp.asarray(x, jnp.float32) for x in states)
    N, n = q.shape
    chunk = int(min(chunk, N))
    n_chunks = -(-N // chunk)
    pad = n_chunks * chunk - N
    valid = jnp.arange(n_chunks * chunk) < N
    q = jnp.concatenate([q, jnp.broadcast_to(q[:1], (pad, n))]).reshape(n_chunks, chunk, n)
    v = jnp.concatenate([v, jnp.broadcast_to(v[:1], (pad, n))]).reshape(n_chunks, chunk, n)
    valid = valid.reshape(n_chunks, chunk)
    a_nom = None if a_nominal is None else jnp.asarray(a_nominal, jnp.float32)

    def body(carry, x):
        lo, hi, s = carry
        qc, vc, ok = x
        M, h = jax.vmap(dynamics)(qc, vc)
        l, u = torque_acc_box(M, h, tau)
        ok2 = jnp.broadcast_to(ok[:, None], l.shape)
        lo = jnp.maximum(lo, jnp.max(jnp.where(ok2, l, -jnp.inf), axis=0))
        hi = jnp.minimum(hi, jnp.min(jnp.where(ok2, u, jnp.inf), axis=0))
        if a_nom is not None:
            s = jnp.minimum(s, jnp.min(jnp.where(ok, box_scale(M, h, tau, a_nom), jnp.inf)))
        return (lo, hi, s), None

    init = (
        jnp.full((n,), -jnp.inf, jnp.float32),
        jnp.full((n,), jnp.inf, jnp.float32),
        jnp.array(jnp.inf, jnp.float32),
    )
    (lo, hi, s), _ = jax.lax.scan(body, init, (q, v, valid))
    return TorqueBounds(lo, hi, s)


__all__ = [
    "TorqueBounds",
    "acc_bounds_from_torque",
    "box_scale",
    "sample_states",
    "torque_acc_box",
    "torque_acc_box_conservative",
]
