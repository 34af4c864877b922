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

from jaxlimits._src.step import Step


def substep_argmin(d, hv, n: int):
    """The ``k`` in ``1..n`` minimising ``f(k) = (d - k hv) / (k (k+1))`` (``hv = h v``), as a float.

    Closed form, no search: ``f(k) - f(k+1) = 2 (2 d - k hv) / (k (k+1) (k+2))``, so ``f`` steps
    down exactly while ``k hv <= 2 d``. For ``hv > 0`` that is an initial run of ``k``: the
    minimiser is ``floor(2 d / hv) + 1`` clipped to ``[1, n]`` (``1`` when ``d < 0``), checked
    once each way against the criterion itself, so a division that rounds across an integer cannot
    move it. For ``hv <= 0`` the sign of ``2 d - k hv`` can change at most once, upward: ``k = n``
    when ``d >= 0`` (``f`` never increases), else the better end, ``k = 1`` iff ``f(1) <= f(n)``,
    i.e. ``(n + 2) d <= n hv``. Piecewise constant in its inputs: callers pass ``stop_gradient``
    values. One division (for ``n > 1``), elementwise: XLA fuses it with its consumer.
    """
    if n == 1:
        return jnp.ones_like(d)
    up = hv > 0
    k = jnp.clip(jnp.floor(2.0 * d / jnp.where(up, hv, 1.0)) + 1.0, 1.0, float(n))
    k = (
        k
        + jnp.where((k < n) & (k * hv <= 2.0 * d), 1.0, 0.0)
        - jnp.where((k > 1) & ((k - 1.0) * hv > 2.0 * d), 1.0, 0.0)
    )
    k_end = jnp.where((d < 0) & ((n + 2.0) * d <= n * hv), 1.0, float(n))
    return jnp.where(up, k, k_end)


def braking_piece(R, a_max, h: float, n: int):
    """The active ``K >= 0`` of ``viability_upper``: the largest with ``P(K) = a_max h^2 K (K + n) / 2 <= R``.

    ``P`` is increasing on ``K >= 0``, so ``K = floor(y)`` with ``y (y + n) = 2 R / (a_max h^2)``,
    ``y = (sqrt(n^2 + 8 R / (a_max h^2)) - n) / 2`` (``0`` for ``R < 0``), checked once each way
    against ``P`` itself, so a square root that rounds across an integer cannot move it. Piecewise
    constant: callers pass a ``stop_gradient`` ``R``.
    """
    rho = jnp.maximum(2.0 * R / (a_max * h * h), 0.0)
    K = jnp.floor((jnp.sqrt(float(n * n) + 4.0 * rho) - n) / 2.0)
    P = lambda K: a_max * h * h * K * (K + n) / 2.0  # noqa: E731
    K = K + jnp.where(P(K + 1.0) <= R, 1.0, 0.0) - jnp.where(P(K) > R, 1.0, 0.0)
    return jnp.maximum(K, 0.0)


class SemiImplicit:
    """MuJoCo's semi-implicit Euler update with ``substeps`` physics steps per control step."""

    integrator = "semi_implicit"  # the name acc_bounds knows it by (for messages and the eager jerk condition)

    def __init__(self, dt: float, substeps: int):
        self.dt = dt
        self.n = substeps
        self.substeps = substeps
        self.h = dt / substeps
        self.period = dt

    def _q_coeffs(self, k):
        """``q_k = q + k h v + c_k a`` with ``c_k = h^2 k (k+1) / 2``."""
        return k * self.h, self.h * self.h * k * (k + 1) / 2.0

    def __eq__(self, other):
        return type(other) is type(self) and other._key() == self._key()

    def __hash__(self):
        return hash((type(self), self._key()))

    def _key(self):
        """Equal discretisations compile to the same code (the object is a static argument of ``jit``)."""
        return (self.dt, self.n)

    # ------------------------------------------------------------ behaviour used by every limit family

    @property
    def roundings_per_step(self) -> int:
        """Rounded position updates per control step (one per substep), for the rounding guard."""
        return self.n

    @property
    def position_gain(self) -> float:
        """``c`` in ``q_T = q + T v + c a`` (a held): ``h^2 n (n + 1) / 2`` (twice the zoh's ``T^2/2`` as n -> inf)."""
        return self.h * self.h * self.n * (self.n + 1) / 2.0

    def integrate(self, q, v, a) -> Step:
        """MuJoCo's update ``v += h a; q += h v`` repeated ``n`` times; extremes over the substep states."""

        def substep(carry, _):
            qk, vk, lo, hi = carry
            vk = vk + self.h * a
            qk = qk + self.h * vk
            return (qk, vk, jnp.minimum(lo, qk), jnp.maximum(hi, qk)), None

        (q1, v1, lo, hi), _ = jax.lax.scan(substep, (q, v, q, q), None, length=self.n)
        return Step(q1, v1, lo, hi)

    def step_peak(self, p, v, a):
        """Largest displacement over the substeps of one step with held ``a`` from ``(p, v)`` (after its start).

        ``p_k = p + k h v + h^2 a k (k+1)/2`` is concave in ``k`` for ``a < 0`` with its real maximiser at
        ``-v/(a h) - 1/2``: its floor, the next integer and ``k = n`` are evaluated (the last covers ``a >= 0``).
        """
        h, n = self.h, self.n
        neg = a < 0
        a_safe = jnp.where(neg, a, -1.0)
        k_star = jnp.where(neg, -jax.lax.stop_gradient(v / a_safe) / h - 0.5, float(n))
        k0 = jnp.floor(jnp.clip(k_star, 1.0, float(n)))
        best = None
        for k in (k0, jnp.minimum(k0 + 1.0, float(n)), jnp.full_like(k0, float(n))):
            pk = p + k * h * v + h * h * a * k * (k + 1.0) / 2.0
            best = pk if best is None else jnp.maximum(best, pk)
        return best

    def crossing_distance(self, d, v):
        """``d'`` of the jerk bounds' crossing-step cubic: the substep positions lie ``h v / 2`` above the zoh curve."""
        return d + 0.5 * self.h * v

    def ramp_roots(self, d, v, delta, i, Vp, s1, s2):
        """Upper bounds of the jerk position threshold from step ``i`` of the endless ramp (see ``jerk._ramp_root``).

        Substep positions are ``p(Kh) + h (v(Kh) - v) / 2``, bound ``2 N(Kh) / (h^2 K (K+1))``; the continuous
        minimiser ``t* = (D3 + sqrt(D3^2 + V' D3 h)) / V'`` and its two integer neighbours (within the step).
        """
        h, n = self.h, float(self.n)
        D3 = d + delta * (s2 - 0.5 * h * s1)
        regular = (D3 > 0) & (Vp > 0)
        t_star = (D3 + jnp.sqrt(jnp.maximum(D3 * D3 + Vp * D3 * h, 0.0))) / jnp.where(regular, Vp, 1.0)
        k_lo, k_hi = jnp.maximum(i * n, 1.0), (i + 1.0) * n
        k0 = jnp.floor(t_star / h)
        out = []
        ks = (
            jnp.where(regular, jnp.clip(k0, k_lo, k_hi), k_lo),
            jnp.where(regular, jnp.clip(k0 + 1.0, k_lo, k_hi), k_hi),
        )
        for K in ks:
            t = K * h
            N = D3 - (Vp - 0.5 * delta * h * i) * t + 0.5 * delta * i * t * t
            out.append(2.0 * N / (h * h * K * (K + 1.0)))
        return out

    def hold_roots(self, d, a_max, P0, V0, r, sp, sv):
        """Upper bounds of the jerk position threshold from the hold phase (see ``jerk._hold_root``).

        ``p_m + D(v_m) <= d`` with ``D`` the maximum of the lines ``h (j x - A h j (j+1)/2)``: the active ``j`` is
        the largest with ``C0 + r A h j + A h^2 j (j-1)/2 <= d`` (a quadratic); it and its neighbours are solved.
        """
        h = self.h
        b = 2.0 * r / h - 1.0
        cc = jnp.maximum(2.0 * (d - P0 + r * V0) / (a_max * h * h), 0.0)
        j_hat = jnp.floor(0.5 * (jnp.sqrt(b * b + 4.0 * cc) - b))
        out = []
        for off in (-1.0, 0.0, 1.0):
            j = jnp.maximum(j_hat + off, 0.0)
            out.append((d - P0 - j * h * V0 + 0.5 * a_max * h * h * j * (j + 1.0)) / (sp + j * h * sv))
        return out

    def end_position_upper(self, d, v):
        """Largest ``a`` with ``q_n <= q_max`` (the one-step 'naive' bound for this model)."""
        bv, ca = self._q_coeffs(self.n)
        return (d - bv * v) / ca

    def position_upper(self, d, v, a_max):
        """Largest ``a`` with ``q_k <= q_max`` for every substep ``k = 1..n``: ``min_k (d - k h v) / c_k``.

        Evaluated at its minimiser ``k = substep_argmin(d, h v, n)`` only (a closed form: ``f(k+1)
        <= f(k)`` iff ``k h v <= 2 d``; ``floor(2 d / (h v)) + 1`` for ``v > 0``, an end otherwise),
        so one division selects and one evaluates, with no candidate axis to reduce. ``k`` only
        selects the piece: no gradient through it.
        """
        h = self.h
        k = substep_argmin(jax.lax.stop_gradient(d), h * jax.lax.stop_gradient(v), self.n)
        bv, ca = self._q_coeffs(k)
        return (d - bv * v) / ca

    def viability_upper(self, d, v, a_max):
        """Largest ``a`` whose next state is upper-viable: ``q_n + D(v_n) <= q_max``.

        With ``x = v_n`` (so ``a = (x - v) / T`` and ``q_n = q + h ((n-1) v + (n+1) x) / 2``) the
        condition is ``L(x) = h (n+1) x / 2 + D(x) <= R = d - h (n-1) v / 2``. ``L`` is the maximum
        of the increasing lines ``L_K(x) = h (n+1) x / 2 + h (K x - a_max h K (K+1) / 2)``
        (``K >= 0``; ``D`` is convex), so the root of ``L(x) = R`` is the *minimum* over ``K`` of
        the roots ``x_K = (2 R / h + a_max h K (K+1)) / (n + 1 + 2 K)``, attained at the active
        piece: the largest ``K`` with ``L(K a_max h) = a_max h^2 K (K + n) / 2 <= R``
        (``braking_piece``, a square root and two checks). One ``x_K`` is evaluated.
        """
        n, h = self.n, self.h
        R = d - h * (n - 1) * v / 2.0
        K = braking_piece(jax.lax.stop_gradient(R), a_max, h, n)
        x = (2.0 * R / h + a_max * h * K * (K + 1.0)) / (n + 1.0 + 2.0 * K)
        return (x - v) / self.dt

    def braking_distance(self, v, a_max):
        """``D(v)``: distance travelled toward the upper limit under full braking (see module doc).

        ``D`` is the maximum of the lines ``h (K v - a_max h K (K+1) / 2)``, ``K >= 0``; the three
        around ``K = floor(v / (a_max h))`` are taken (a wrong ``K`` only gives a smaller value),
        unrolled elementwise (no candidate axis: a stacked axis is reduced outside XLA's loop fusion).
        """
        h = self.h
        vp = jnp.maximum(v, 0.0)
        k0 = jnp.floor(jax.lax.stop_gradient(vp) / (a_max * h))
        dist = None
        for off in (-1.0, 0.0, 1.0):
            K = jnp.maximum(k0 + off, 0.0)
            line = h * (K * vp - a_max * h * K * (K + 1.0) / 2.0)
            dist = line if dist is None else jnp.maximum(dist, line)
        return dist
