"""The one "is this value traced?" test used by every eager check of the core."""

from __future__ import annotations

from typing import Any

import jax


def is_traced(x: Any) -> bool:
    """True when ``x`` is a JAX tracer (inside ``jit``/``vmap``/``grad``), so its value is unknown."""
    return isinstance(x, jax.core.Tracer)
