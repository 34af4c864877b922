"""Meguenani, Padois and Bidaud's jerk-aware bounds, eqs. (39)-(40), as a baseline (``method="jerk_paper"``).

Faithful to the paper, including what makes it heuristic:

* The model of its formulas is the paper's eqs. (11), (28), (48): explicit Euler *positions*
  ``q_{k+1} = q_k + dt qd_k``, velocities ``qd_{k+1} = qd_k + dt qdd_k``, accelerations ramped by the
  jerk; the formulas do not depend on ``integrator``/``substeps``. Those name the model ``viable``
  refers to: as for every method, membership of the exact viability kernel (here that of the exact
  jerk-aware bounds, ``jerk.py``, for the discretisation given), so a user can count how often the
  paper's bounds leave it. ``rounding_guard`` tightens the limits as for the exact jerk bounds.
* Velocity, eqs. (13)-(14): ``a <= (v_M - v) / (n1 dt) - (n1 - 1)/2 jm dt`` with the integer
  ``n1 >= 1`` minimising it; (14) gives the real minimiser ``sqrt(2 (v_M - v) / J) / dt`` and we
  evaluate the two integers around it (the right-hand side is convex in ``n1``).
* Position with deceleration and jerk, eq. (36): ``n7`` steps of jerk ``jm`` then ``n9`` steps of
  deceleration ``am``; ``(n7, n9)`` minimise the right-hand side over the paper's grid
  ``1 <= n7 <= 500``, ``3 <= n9 <= 100`` (Appendix E: "all the combinations ... are to be tried"),
  done here as a vectorised brute force (49,000 pairs per joint).
* Final bounds, eqs. (39)-(40): ``min(f_vel, f_pos, a_max, a_prev + J dt)`` and the mirror image, the
  terms ``velocity``, ``position``, ``acceleration``, ``jerk`` (the paper has no viability test).

Typos and the readings chosen (all checked against the derivation they come from):

* Eq. (15): the first denominator reads ``n1 dt``; the derivation mirrors (13) with ``n2``, so it is
  ``n2 dt``. The jerk there is printed as ``qdd_M`` (an acceleration); by (12)-(13) it is the
  jerk ``qddd_M``. Eq. (16) as printed gives a negative ``n2`` (``-sqrt(..)/(qddd_M dt)`` with
  ``qddd_M > 0``); the mirror of (14) is ``n2 = sqrt(2 (v - v_m) / J) / dt``, used here. (Eq. (17)
  also swaps the names ``f1``/``f2`` relative to (39)-(40); harmless.)
* Eq. (35) (Appendix eq. 55): the last term reads ``(n9^2 - n7)/2 qdd_m dt^2``; expanding (34) with
  (29) and (12) gives ``(n9^2 - n9)/2``, which is also what (36) uses. We use (36).
* Eq. (37) (and 57): the cubic coefficient reads ``n3^2/6 + n7^2/2 + n7/3``; from (29) it is
  ``n7^3/6 - n7^2/2 + n7/3`` as in (36) and (38). (37) is the velocity-level form, not used here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


from jaxlimits._src.jerk import Jerk, jerk_arrays
from jaxlimits._src.joint_state import JointArrays, guard_limits
from jaxlimits._src.limit import AccelerationLimit, Terms, toward_upper_side
from jaxlimits._src.tracing import is_traced

N7 = (1, 500)
N9 = (3, 100)


def velocity_upper(v, v_max, T, J):
    """Eqs. (13)-(14): the integer ``n1 >= 1`` nearest the real minimiser, both sides evaluated."""
    R = jnp.maximum(v_max - v, 0.0)
    n_real = jnp.sqrt(2.0 * jax.lax.stop_gradient(R) / J) / T
    best = None
    for n1 in (jnp.maximum(jnp.floor(n_real), 1.0), jnp.maximum(jnp.ceil(n_real), 1.0)):
        val = (v_max - v) / (n1 * T) + (n1 - 1.0) / 2.0 * J * T
        best = val if best is None else jnp.minimum(best, val)
    return best


def position_upper(d, v, T, A, J):
    """Eq. (36) minimised over the grid ``1 <= n7 <= 500``, ``3 <= n9 <= 100`` (brute force)."""
    n9 = jnp.arange(N9[0], N9[1] + 1, dtype=d.dtype).reshape((1,) * d.ndim + (-1,))
    d_, v_, A_, J_ = (x[..., None] for x in (d, v, A, J))

    def rhs(n7):
        B = (n7 * n7 - n7) / 2.0 + n7 * n9
        C = n7**3 / 6.0 - n7 * n7 / 2.0 + n7 / 3.0 + n9 * (n7 * n7 - n7) / 2.0
        val = d_ / (B * T * T) - (n7 + n9) * v_ / (B * T) + (n9 * n9 - n9) / (2.0 * B) * A_ + C / B * J_ * T
        return jnp.min(val, axis=-1)

    def body(k, best):
        return jnp.minimum(best, rhs(k.astype(d.dtype)))

    return jax.lax.fori_loop(N7[0] + 1, N7[1] + 1, body, rhs(jnp.asarray(float(N7[0]), d.dtype)))


def _paper_terms(a: JointArrays, model, rounding_guard: bool) -> Terms:
    q, v, a_prev, q_min, q_max, v_max, a_max, j_max = a
    T = model.period
    if rounding_guard:
        stop_steps = jnp.ceil(v_max / (a_max * T)) + jnp.ceil(3.0 * a_max / (j_max * T)) + 1.0
        q_min, q_max, v_max = guard_limits(q_min, q_max, v_max, a_max, model.roundings_per_step + 2, stop_steps)
    span = q_max - q_min
    qc = jnp.clip(q, q_min - span, q_max + span)
    vc = jnp.clip(v, -2.0 * v_max, 2.0 * v_max)

    def two(x, y):
        return jnp.stack([x, y])

    vm2, am2, jm2 = two(v_max, v_max), two(a_max, a_max), two(j_max, j_max)
    vel = velocity_upper(two(vc, -vc), vm2, T, jm2)
    pos = position_upper(two(q_max - qc, qc - q_min), two(vc, -vc), T, am2, jm2)
    upper = {"acceleration": a_max, "jerk": a_prev + j_max * T, "velocity": vel[0], "position": pos[0]}
    lower = {"acceleration": -a_max, "jerk": a_prev - j_max * T, "velocity": -vel[1], "position": -pos[1]}
    return Terms(upper, lower, jnp.zeros(q.shape, bool), toward_upper_side(q, v, q_min, q_max))


_paper_terms_jit = jax.jit(_paper_terms, static_argnames=("model", "rounding_guard"))


class JerkPaper(AccelerationLimit):
    """Meguenani et al.'s eqs. (39)-(40) (module docstring); ``viable`` from the exact jerk kernel (``Jerk``)."""

    needs_a_prev = True

    def __init__(self, limits, model, rounding_guard: bool = True):
        self.kernel = Jerk(limits, model, rounding_guard)  # validates j_max and the room to recover
        self.limits, self.model, self.rounding_guard = limits, model, bool(rounding_guard)

    def evaluate(self, q, v, a_prev=None) -> Terms:
        a = jerk_arrays(q, v, a_prev, self.limits)
        if is_traced(self.model.period):
            t = _paper_terms(a, self.model, self.rounding_guard)
        else:
            t = _paper_terms_jit(a, model=self.model, rounding_guard=self.rounding_guard)
        return t._replace(viable=self.kernel.viable(q, v, a_prev))
