"""One control step of a joint under a held acceleration, for either discretisation."""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits._src.discretisation import make_discretisation
from jaxlimits._src.step import Step


def integrate_step(q, v, a, dt, integrator: str = "zoh", substeps: int = 1) -> Step:
    """Advance ``(q, v)`` [rad, rad/s] by one control step of length ``dt`` [s] with acceleration ``a`` held.

    ``zoh``: the exact parabola of Del Prete's eq. (5), with its interior extremum at ``t = -v / a`` when
    that lies inside the step. ``semi_implicit``: MuJoCo's update ``v += h a; q += h v`` repeated
    ``substeps`` times (``h = dt / substeps``). Shapes broadcast; returns ``Step`` of the broadcast shape.
    """
    model = make_discretisation(dt, integrator, substeps)
    q, v, a = jnp.broadcast_arrays(*(jnp.asarray(x) for x in (q, v, a)))
    return model.integrate(q, v, a)


__all__ = ["Step", "integrate_step"]
