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
from jaxlimits._src.step import Step


class ZeroOrderHold:
    """The paper's model; positions are bounded in continuous time inside the step."""

    integrator = "zoh"  # the name acc_bounds knows it by (for messages and the eager jerk condition)
    substeps = 1

    def __init__(self, dt: float):
        self.dt = dt
        self.period = dt

    def __eq__(self, other):
        return type(other) is type(self) and other._key() == self._key()

    def __hash__(self):
        return hash((type(self), self._key()))

    def _key(self):
        """Equal discretisations compile to the same code (the object is a static argument of ``jit``)."""
        return (self.dt,)

    # ------------------------------------------------------------ behaviour used by every limit family

    @property
    def roundings_per_step(self) -> int:
        """Rounded operations on the position per control step (``q + T v + T^2 a / 2``), for the rounding guard."""
        return 3

    @property
    def position_gain(self) -> float:
        """``c`` in ``q_T = q + T v + c a`` (a held over the step): ``T^2 / 2`` (eq. 5)."""
        return 0.5 * self.dt * self.dt

    def integrate(self, q, v, a) -> Step:
        """The exact parabola of eq. (5), with its interior extremum at ``t = -v / a`` when inside the step."""
        T = self.dt
        q1 = q + T * v + 0.5 * T * T * a
        v1 = v + T * a
        a_safe = jnp.where(a != 0, a, 1.0)
        t_ext = jnp.where(a != 0, -v / a_safe, -1.0)
        inside = (t_ext > 0) & (t_ext < T)
        q_ext = jnp.where(inside, q + t_ext * v + 0.5 * t_ext * t_ext * a, q)
        lo = jnp.minimum(jnp.minimum(q, q1), q_ext)
        hi = jnp.maximum(jnp.maximum(q, q1), q_ext)
        return Step(q1, v1, lo, hi)

    def step_peak(self, p, v, a):
        """Largest displacement reached during one step with held ``a`` from ``(p, v)`` (after its start):
        the vertex ``p - v^2 / (2 a)`` when the velocity crosses zero inside the step, else the end."""
        T = self.dt
        end = p + T * v + 0.5 * T * T * a
        inside = (v > 0) & (a < 0) & (v < -a * T)
        a_safe = jnp.where(inside, a, -1.0)
        return jnp.where(inside, p - v * v / (2.0 * a_safe), end)

    def crossing_distance(self, d, v):
        """``d'`` of the jerk bounds' crossing-step cubic: ``d`` itself (continuous-time positions)."""
        return d

    def ramp_roots(self, d, v, delta, i, Vp, s1, s2):
        """Upper bounds of the jerk position threshold from step ``i`` of the endless ramp (see ``jerk._ramp_root``).

        The bound at ``t`` is ``(D' - V' t + delta i t^2/2) / (t^2/2)``, minimised over the step at
        ``t* = 2 D' / V'`` (value ``delta i - V'^2 / (2 D')``) if inside, else at the step's end (its start is
        the previous candidate step's end). Step 0 excludes the start (``v <= 0``: its end).
        """
        T = self.dt
        Dp = d + delta * s2
        t_end = (i + 1.0) * T
        end_val = 2.0 * (Dp - Vp * t_end) / (t_end * t_end)
        inside = (Dp > 0) & (Vp > 0) & (2.0 * Dp <= t_end * Vp) & (2.0 * Dp >= i * T * Vp)
        vertex = jnp.where(inside, -Vp * Vp / (2.0 * jnp.where(inside, Dp, 1.0)), jnp.inf)
        vertex = jnp.where((i == 0) & (v > 0) & (Dp <= 0), -jnp.inf, vertex)
        return [jnp.minimum(end_val, vertex) + delta * i]

    def hold_roots(self, d, a_max, P0, V0, r, sp, sv):
        """Upper bound of the jerk position threshold from the hold phase (see ``jerk._hold_root``).

        ``p_m + v_m^2 / (2 A) = d`` is a quadratic in ``x = v_m``: ``2 A C / (A r + sqrt(A^2 r^2 + 2 A C))``
        with ``C = d - P0 + r V0`` (``C < 0``: ``x = 0``).
        """
        C = jnp.maximum(d - P0 + r * V0, 0.0)
        ar = a_max * r
        x = 2.0 * a_max * C / (ar + jnp.sqrt(ar * ar + 2.0 * a_max * C))
        return [(x - V0) / sv]

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
