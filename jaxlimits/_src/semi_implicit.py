"""Semi-implicit Euler model of MuJoCo/MJX (Euler and implicitfast integrators, no damping).

A control step of length ``T`` is ``n`` physics substeps of ``h = T / n`` with the same
acceleration ``a``:  ``v_k = v_{k-1} + h a``,  ``q_k = q_{k-1} + h v_k``  (k = 1..n), so

    v_k = v + k h a,        q_k = q + k h v + h^2 a k (k + 1) / 2.

The position gains ``h^2 a`` per substep, not the zero-order hold's ``h^2 a / 2``; the constraints
hold at the simulator's states (every substep), which is all MuJoCo ever has.

Derivation of the exact viable set (see ``docs/derivations.md`` for the full text):

* Full braking ``a = -a_max`` at every substep is the pointwise lowest trajectory of any admissible
  future (``v_k >= v - k h a_max`` by induction, hence ``q_k >=`` its position). So the state is
  upper-viable only if that trajectory's peak stays below ``q_max``. The peak is the sum of the
  positive velocities times ``h``:

      D(v) = h * sum_{k >= 1} max(v - k h a_max, 0) = h (K v - a_max h K (K + 1) / 2),
      K = floor(v / (a_max h)),

  a convex, piecewise-linear, increasing function (the discrete braking distance; as ``h -> 0`` it
  tends to ``v^2 / (2 a_max)``).  It does not depend on ``n``: braking never needs to switch.
* Conversely, when ``q_max - q_min >= a_max T^2`` and ``v_max >= a_max T`` (Del Prete's condition
  (11) with ``T = n h``), a state with ``q + D(v) <= q_max``, ``q - D(-v) >= q_min`` and
  ``|v| <= v_max`` can always continue: braking overshoots zero velocity by at most ``a_max T``
  and travels back at most ``a_max T^2`` before it can be stopped. So this set is the viability
  kernel, and the bounds below are exact. The tests check both claims against a long-horizon LP.

Every function works on the upper side (``d = q_max - q``); see ``zoh.py``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxlimits._src.safe_math import candidates


class SemiImplicit:
    """MuJoCo's semi-implicit Euler update with ``substeps`` physics steps per control step."""

    name = "semi_implicit"

    def __init__(self, dt: float, substeps: int):
        self.dt = dt
        self.n = substeps
        self.h = dt / substeps
        self.period = dt

    def _q_coeffs(self, k):
        """``q_k = q + k h v + c_k a`` with ``c_k = h^2 k (k+1) / 2``."""
        return k * self.h, self.h * self.h * k * (k + 1) / 2.0

    def end_position_upper(self, d, v):
        """Largest ``a`` with ``q_n <= q_max`` (the one-step 'naive' bound for this model)."""
        bv, ca = self._q_coeffs(self.n)
        return (d - bv * v) / ca

    def position_upper(self, d, v, a_max):
        """Largest ``a`` with ``q_k <= q_max`` for every substep ``k = 1..n``: ``min_k (d - k h v) / c_k``.

        For ``v > 0, d >= 0`` the real-valued ``k -> (d - k h v) / (k (k+1))`` is unimodal with its
        minimum at ``k* = (d + sqrt(d^2 + h v d)) / (h v)``; the integers around ``k*`` (clipped to
        ``[1, n]``, four of them so that rounding in ``k*`` cannot miss the minimiser) are
        evaluated exactly. Otherwise the minimum is at an end: ``k = n`` for ``v <= 0, d >= 0``
        (decreasing), ``k = 1`` or ``k = n`` for a state already past the limit (``d < 0``, best
        effort), so both ends are always candidates. ``k*`` only selects integers: no gradient.
        """
        n, h = self.n, self.h
        sd, sv = jax.lax.stop_gradient(d), jax.lax.stop_gradient(v)
        interior = (sv > 0) & (sd >= 0)
        sd_i = jnp.where(interior, sd, 0.0)
        sv_i = jnp.where(interior, sv, 1.0)
        k_star = (sd_i + jnp.sqrt(sd_i * sd_i + h * sv_i * sd_i)) / (h * sv_i)
        k_star = jnp.where(interior, jnp.clip(k_star, 0.0, float(n)), float(n))
        # the four integers around k*, and both ends (the minimiser for v <= 0 or d < 0)
        k = candidates(jnp.floor(k_star), (-1.0, 0.0, 1.0, 2.0, -n, n), 1.0, float(n))
        bv, ca = self._q_coeffs(k)
        return jnp.min((d[..., None] - bv * v[..., None]) / ca, axis=-1)

    def viability_upper(self, d, v, a_max):
        """Largest ``a`` whose next state is upper-viable: ``q_n + D(v_n) <= q_max``.

        With ``x = v_n`` (so ``a = (x - v) / T`` and ``q_n = q + h ((n-1) v + (n+1) x) / 2``) the
        condition is ``L(x) = h (n+1) x / 2 + D(x) <= R = d - h (n-1) v / 2``. ``L`` is the maximum
        of the increasing lines ``L_K(x) = h (n+1) x / 2 + h (K x - a_max h K (K+1) / 2)``
        (``K >= 0``; ``D`` is convex), so the root of ``L(x) = R`` is the *minimum* over ``K`` of
        the roots ``x_K = (2 R / h + a_max h K (K+1)) / (n + 1 + 2 K)``. The active ``K`` is the
        largest with ``L(K a_max h) = a_max h^2 K (K + n) / 2 <= R``; its neighbours are included,
        so rounding can only make the result smaller (safer), never larger.
        """
        n, h = self.n, self.h
        R = d - h * (n - 1) * v / 2.0
        rho = jnp.maximum(2.0 * jax.lax.stop_gradient(R) / (a_max * h * h), 0.0)
        k_hat = jnp.floor((-n + jnp.sqrt(float(n * n) + 4.0 * rho)) / 2.0)
        K = candidates(k_hat, (-1.0, 0.0, 1.0), 0.0, jnp.inf)
        x = (2.0 * R[..., None] / h + a_max[..., None] * h * K * (K + 1.0)) / (n + 1.0 + 2.0 * K)
        return (jnp.min(x, axis=-1) - v) / self.dt

    def braking_distance(self, v, a_max):
        """``D(v)``: distance travelled toward the upper limit under full braking (see module doc)."""
        h = self.h
        vp = jnp.maximum(v, 0.0)
        K = candidates(jnp.floor(jax.lax.stop_gradient(vp) / (a_max * h)), (-1.0, 0.0, 1.0), 0.0, jnp.inf)
        dist = h * (K * vp[..., None] - a_max[..., None] * h * K * (K + 1.0) / 2.0)
        return jnp.max(dist, axis=-1)
