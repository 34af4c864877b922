"""One control step of a joint under a held acceleration, for both discretisations of ``bounds``."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxlimits._src.bounds import make_model


class Step(NamedTuple):
    """Result of one control step, each ``(..., n)``.

    q, v: state at the end of the step. q_low, q_high: the smallest and largest position reached
    during the step (continuous time for ``zoh``; the substep states for ``semi_implicit``).
    """

    q: jax.Array
    v: jax.Array
    q_low: jax.Array
    q_high: jax.Array


def integrate_step(q, v, a, dt, integrator: str = "zoh", substeps: int = 1) -> Step:
    """Advance ``(q, v)`` by one control step of length ``dt`` [s] with acceleration ``a`` held.

    ``zoh``: the exact parabola of Del Prete's eq. (5), with its interior extremum at
    ``t = -v / a`` when that lies inside the step. ``semi_implicit``: MuJoCo's update
    ``v += h a; q += h v`` repeated ``substeps`` times (``h = dt / substeps``).
    """
    model = make_model(dt, integrator, substeps)
    q, v, a = jnp.broadcast_arrays(*(jnp.asarray(x) for x in (q, v, a)))
    if integrator == "zoh":
        T = model.dt
        q1 = q + T * v + 0.5 * T * T * a
        v1 = v + T * a
        a_safe = jnp.where(a != 0, a, 1.0)
        t_ext = jnp.where(a != 0, -v / a_safe, -1.0)
        inside = (t_ext > 0) & (t_ext < T)
        q_ext = jnp.where(inside, q + t_ext * v + 0.5 * t_ext * t_ext * a, q)
        lo = jnp.minimum(jnp.minimum(q, q1), q_ext)
        hi = jnp.maximum(jnp.maximum(q, q1), q_ext)
        return Step(q1, v1, lo, hi)

    def substep(carry, _):
        qk, vk, lo, hi = carry
        vk = vk + model.h * a
        qk = qk + model.h * vk
        return (qk, vk, jnp.minimum(lo, qk), jnp.maximum(hi, qk)), None

    (q1, v1, lo, hi), _ = jax.lax.scan(substep, (q, v, q, q), None, length=model.n)
    return Step(q1, v1, lo, hi)
