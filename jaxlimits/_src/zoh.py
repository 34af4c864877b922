"""Zero-order-hold model (Del Prete 2018, eq. 1 and 5): the paper's discretisation.

The acceleration ``a`` is held over the control step ``T``; inside the step
``q(t) = q + t v + t^2 a / 2`` and ``v(t) = v + t a`` for continuous ``t in [0, T]``.

Every function works on the *upper* side of one joint: ``d = q_max - q`` is the distance to the
upper limit and returns the largest admissible acceleration (or a distance). The lower side is the
mirror image (``d = q - q_min``, ``v -> -v``, result negated), see ``bounds.py``.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits._src.safe_math import tiny_floor


class ZeroOrderHold:
    """The paper's model; positions are bounded in continuous time inside the step."""

    name = "zoh"

    def __init__(self, dt: float):
        self.dt = dt
        self.period = dt

    def end_position_upper(self, d, v):
        """Largest ``a`` with ``q(T) <= q_max`` (eq. 2, 20): ``2 (d - T v) / T^2``."""
        T = self.dt
        return 2.0 * (d - T * v) / (T * T)

    def position_upper(self, d, v, a_max):
        """Largest ``a`` with ``q(t) <= q_max`` for all ``t in [0, T]`` (eqs. 13-22, Alg. 1).

        ``min_{t in (0,T]} 2 (d - t v) / t^2``: with ``s = 1/t`` this is the convex ``2 d s^2 - 2 v s``
        over ``s >= 1/T``. Its minimum is inside (the position peaks inside the step, eq. 17) iff
        ``v > 0`` and ``v T >= 2 d``, giving ``-v^2 / (2 d)`` (eq. 19); else it is the end value
        (eq. 20). For a state past the limit (``d < 0``) moving away, the end value is kept: the
        best effort is to be back inside at the end of the step.

        ``-v^2/(2d)`` is computed as ``-v^2 / (2 max(d, v^2/(2 a_max), floor))``: identical whenever
        the state is viable (then ``d >= v^2/(2 a_max)``), and ``-a_max`` (full braking) otherwise,
        so it never divides by zero.
        """
        T = self.dt
        peak_inside = (v > 0) & (v * T >= 2.0 * d)
        d_safe = jnp.where(peak_inside, jnp.maximum(jnp.maximum(d, v * v / (2.0 * a_max)), tiny_floor(d.dtype)), 1.0)
        return jnp.where(peak_inside, -v * v / (2.0 * d_safe), self.end_position_upper(d, v))

    def viability_upper(self, d, v, a_max):
        """Largest ``a`` whose next state is upper-viable: ``v1 <= sqrt(2 a_max (q_max - q1))`` (24).

        Solved for the next velocity ``x = v + T a`` (so ``q1 = q + T (v + x) / 2``): the condition
        ``x^2 + a_max T x - c <= 0`` with ``c = a_max (2 d - T v)`` has the root
        ``x = 2 c / (a_max T + sqrt(a_max^2 T^2 + 4 c))`` (the cancellation-free form of eq. 28);
        for ``c < 0`` only ``x <= 0`` remains (eq. 25), whose ``q1 <= q_max`` part is the position
        bound. The denominator is ``>= a_max T > 0``: no NaN, bounded derivative.
        """
        T = self.dt
        c = jnp.maximum(a_max * (2.0 * d - T * v), 0.0)
        x = 2.0 * c / (a_max * T + jnp.sqrt((a_max * T) ** 2 + 4.0 * c))
        return (x - v) / T

    def braking_distance(self, v, a_max):
        """Distance travelled toward the upper limit under full braking: ``max(v,0)^2 / (2 a_max)`` (8)."""
        vp = jnp.maximum(v, 0.0)
        return vp * vp / (2.0 * a_max)
