"""Composition of limits: the intersection of several ``Bounds``, with one documented conflict rule."""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp

from jaxlimits._src.limit import Bounds, Constraint


class Intersection(NamedTuple):
    """The composed limits.

    bounds: the composed ``Bounds``. conflict: ``(..., n)`` bool, joints where a later limit had to yield.
    G, h: the halfspace rows of every input ``Constraint`` concatenated (``None`` when none had rows).
    """

    bounds: Bounds
    conflict: jax.Array
    G: Optional[jax.Array] = None
    h: Optional[jax.Array] = None


def _parts(item):
    if isinstance(item, Constraint):
        return item.bounds, item.G, item.h
    if isinstance(item, Bounds):
        return item, None, None
    raise TypeError(f"intersect takes Bounds or Constraint values, got {type(item).__name__}")


def intersect(first, *others) -> Intersection:
    """Intersect limits in priority order: ``first`` (e.g. the viability bounds), then each of ``others``.

    The conflict rule: where the interval so far and the next one overlap, the result is their
    intersection; where they are disjoint (per joint) the interval so far wins and collapses to its
    end nearest the other (``lower`` when it lies above the other, else ``upper``) — the least
    demanding action the higher-priority limits allow, for the viability bounds their braking side.
    Dropping it would trade a certain limit violation for, e.g., a torque one that the motors' clamp
    then measures. Never silent: ``conflict`` marks every joint where a later limit had to yield.

    Each item is a ``Bounds`` or a ``Constraint`` (a box with halfspace rows); ``viable`` is the
    conjunction; the rows (``G``, ``h``) are concatenated. All inputs broadcast.
    """
    (lower, upper, viable), G, h = _parts(first)
    rest = [_parts(b) for b in others]
    shape = jnp.broadcast_shapes(jnp.shape(lower), *(jnp.shape(b.lower) for b, _, _ in rest))

    def full(x):  # explicit broadcasting (rank promotion may be set to raise)
        return jnp.broadcast_to(x, shape)

    lower, upper, viable = full(lower), full(upper), full(viable)
    conflict = jnp.zeros(shape, bool)
    for b, G_b, h_b in rest:
        b = Bounds(full(b.lower), full(b.upper), full(b.viable))
        lo, hi = jnp.maximum(lower, b.lower), jnp.minimum(upper, b.upper)
        disjoint = lo > hi
        keep = jnp.where(lower > b.upper, lower, upper)
        lower, upper = jnp.where(disjoint, keep, lo), jnp.where(disjoint, keep, hi)
        viable = viable & b.viable
        conflict = conflict | disjoint
        G = _cat(G, G_b, -2)
        h = _cat(h, h_b, -1)
    return Intersection(Bounds(lower, upper, viable), conflict, G, h)


def _cat(a, b, axis):
    if a is None or b is None:
        return b if a is None else a
    return jnp.concatenate([a, b], axis=axis)
