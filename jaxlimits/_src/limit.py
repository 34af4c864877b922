"""The one interface every acceleration limit implements, and the one type it returns.

A limit family (``naive``, ``viability``, ``jerk``, ``jerk_paper``, the torque box, the impact speed
cap, or one a user writes) is a class with one method, ``evaluate(q, v, a_prev) -> Terms``: each of
its constraints' own threshold on the next step's joint acceleration, per side, plus whether the
state is viable. Everything else is shared and written once here (in the manner of mink's
``Limit.compute_qp_inequalities``):

* ``bounds`` = ``combine(evaluate(...))``: the upper bound is the minimum of the upper terms, the lower
  bound the maximum of the lower terms, both clipped into the ``"acceleration"`` box (every family
  has that term: ``[-a_max, a_max]``, or for the jerk bounds the box the jerk lets this step reach);
  where the two sides then conflict (``lower > upper``: the state is not viable) the interval
  collapses to the braking action on the side the joint is moving toward (at rest: the side of the
  range's midpoint it is on), the one conflict rule of every family (``brake_on_conflict``).
* ``terms`` = the terms themselves (``jl.bound_terms``), so a diagnostic can never disagree with the
  bounds: ``bounds`` is their min/max, clipped and resolved.

``Bounds.viable`` means the same for every family: the state lies in the viability kernel of the
constraints the family names (some admissible future satisfies them forever, under the family's
discretisation). For a family that constrains only the action at the current state (the torque box,
the impact cap), that is "its set of admissible accelerations is not empty here".
"""

from __future__ import annotations

import abc
import functools
from typing import ClassVar, NamedTuple, Optional

import jax
import jax.numpy as jnp

from jaxlimits._src.safe_math import materialize


class Bounds(NamedTuple):
    """Admissible joint accelerations for the next control step.

    lower, upper: ``(..., n)`` [rad/s^2], ``lower <= upper`` always.
    viable: ``(..., n)`` bool, whether the current state lies in the viability kernel of the limits
      (see ``jaxlimits._src.limit``). Where it is False the interval is the best-effort braking action;
      for a NaN state (no side to brake toward) ``lower = upper = 0``.
    """

    lower: jax.Array
    upper: jax.Array
    viable: jax.Array


class Constraint(NamedTuple):
    """A limit's full answer: its box ``bounds`` and its halfspace rows ``G a <= h``.

    G, h: ``(..., m, n)`` and ``(..., m)`` for limits that are not a box per joint (the impact speed
    cap); ``None`` (no rows) for box limits. ``jl.intersect`` concatenates them; ``jl.solve_box_qp``
    projects onto the box and the rows.
    """

    bounds: Bounds
    G: Optional[jax.Array] = None
    h: Optional[jax.Array] = None


class Terms(NamedTuple):
    """What a limit family computes for one state (``AccelerationLimit.evaluate``).

    upper, lower: ``{constraint name: (..., n) array}`` [rad/s^2], each constraint's own threshold on
      that side; both contain ``"acceleration"``, the box every bound is clipped into.
    viable: ``(..., n)`` bool, membership of the family's viability kernel.
    toward_upper: ``(..., n)`` bool, the side a conflict brakes toward (``toward_upper_side``).
    G, h: optional halfspace rows (see ``Bounds``).
    """

    upper: dict
    lower: dict
    viable: jax.Array
    toward_upper: jax.Array
    G: Optional[jax.Array] = None
    h: Optional[jax.Array] = None


def toward_upper_side(q, v, q_min, q_max):
    """The side a joint is moving toward: ``v > 0``, or at rest the side of the range's midpoint it is on."""
    return (v > 0) | ((v == 0) & (2.0 * q >= q_min + q_max))


def brake_on_conflict(lower, upper, toward_upper):
    """The one conflict rule: where ``lower > upper`` both collapse to the bound of the side moved toward.

    That bound is the braking action of that side (``-a_max``/``+a_max`` unless less suffices): a
    non-viable state keeps braking toward safety instead of getting an empty interval.
    """
    conflict = lower > upper
    brake = jnp.where(toward_upper, upper, lower)
    return jnp.where(conflict, brake, lower), jnp.where(conflict, brake, upper)


def _reduce(op, values):
    return functools.reduce(op, list(values))


def combine(terms: Terms, fuse_sides: bool = False) -> Bounds:
    """``Bounds`` from ``Terms``: min/max per side, clipped into the ``"acceleration"`` box, then the conflict rule.

    ``fuse_sides``: end each side in ``materialize`` (one XLA loop per side; the jerk bounds need it).
    """
    up = _reduce(jnp.minimum, terms.upper.values())
    lo = _reduce(jnp.maximum, terms.lower.values())
    if fuse_sides:
        up, lo = materialize(up), -materialize(-lo)
    box_lo, box_hi = terms.lower["acceleration"], terms.upper["acceleration"]
    lower, upper = brake_on_conflict(jnp.clip(lo, box_lo, box_hi), jnp.clip(up, box_lo, box_hi), terms.toward_upper)
    return Bounds(lower, upper, terms.viable)


def nan_state_rule(bounds: Bounds, q, v, a_prev=None) -> Bounds:
    """A joint whose state (``q``, ``v``, or ``a_prev``; those given) is NaN has no side to brake toward: its
    bounds are ``lower = upper = 0`` and it is not viable (+-inf and huge states brake as usual)."""
    shape = bounds.lower.shape
    state = [jnp.broadcast_to(jnp.isnan(x), shape) for x in (q, v, a_prev) if x is not None]
    if not state:  # a limit of the action alone (the torque box)
        return bounds
    nan = functools.reduce(jnp.logical_or, state)
    zero = jnp.zeros_like(bounds.lower)
    return Bounds(jnp.where(nan, zero, bounds.lower), jnp.where(nan, zero, bounds.upper), bounds.viable & ~nan)


class AccelerationLimit(abc.ABC):
    """One family of constraints on the next control step's joint accelerations.

    Implement ``evaluate``; ``bounds`` and ``terms`` are shared. Shapes: ``q``, ``v``, ``a_prev``
    ``(..., n)`` [rad, rad/s, rad/s^2]; every returned array ``(..., n)`` in the state's dtype.
    Construction validates the configuration eagerly (``ValueError`` naming the field and value).
    """

    #: whether ``a_prev`` (the previous step's accelerations) is part of the state
    needs_a_prev: ClassVar[bool] = False
    #: end each side in one XLA loop (see ``combine``)
    fuse_sides: ClassVar[bool] = False
    #: whether every acceleration in the bounds of a viable state keeps it viable (safe forever by induction);
    #: False for the baselines (``naive``, ``jerk_paper``), which the contract test shows to overshoot
    guarantees_safety: ClassVar[bool] = False
    #: whether the limit has halfspace rows (then ``bounds`` alone would drop them: use ``constraint``)
    has_rows: ClassVar[bool] = False

    @abc.abstractmethod
    def evaluate(self, q, v, a_prev=None) -> Terms:
        """Each constraint's threshold per side, and viability, at the state (see ``Terms``)."""

    def bounds(self, q, v, a_prev=None) -> Bounds:
        """The admissible interval of the next step's accelerations (``combine`` of ``evaluate``).

        Refused (``TypeError``) for a limit with halfspace rows, which a box cannot carry: use ``constraint``.
        """
        if self.has_rows:
            raise TypeError(
                f"{type(self).__name__} is a halfspace, not a box per joint: use .constraint() "
                "(Bounds and rows G a <= h) or jl.intersect"
            )
        return nan_state_rule(combine(self.evaluate(q, v, a_prev), self.fuse_sides), q, v, a_prev)

    def constraint(self, q, v, a_prev=None) -> Constraint:
        """The box and the halfspace rows (``None`` for a box limit)."""
        t = self.evaluate(q, v, a_prev)
        return Constraint(nan_state_rule(combine(t, self.fuse_sides), q, v, a_prev), t.G, t.h)

    def terms(self, q, v, a_prev=None) -> dict:
        """``{"upper": {name: array}, "lower": {name: array}}``: what ``bounds`` takes the min/max of."""
        t = self.evaluate(q, v, a_prev)
        return {"upper": t.upper, "lower": t.lower}

    def viable(self, q, v, a_prev=None):
        """``(..., n)`` bool: membership of the family's viability kernel."""
        return self.evaluate(q, v, a_prev).viable


def mirror(upper_side, a):
    """The lower side's terms from the upper side's function: ``d = q - q_min``, ``v -> -v`` (and ``a_prev``), negated.

    ``upper_side(d, v, a_prev) -> {name: threshold}``; returns the lower-side dict.
    """
    ap = None if a.a_prev is None else -a.a_prev
    return {k: -t for k, t in upper_side(a.q - a.q_min, -a.v, ap).items()}
