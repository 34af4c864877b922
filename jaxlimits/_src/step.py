"""``Step``: the result of advancing joints by one control step (shared by every discretisation)."""

from __future__ import annotations

from typing import NamedTuple

import jax


class Step(NamedTuple):
    """Result of one control step, each ``(..., n)``.

    q, v: state at the end of the step [rad, rad/s]. q_low, q_high: the smallest and largest position
    reached during the step (continuous time for ``zoh``; the substep states for ``semi_implicit``).
    """

    q: jax.Array
    v: jax.Array
    q_low: jax.Array
    q_high: jax.Array
