"""Small numerical guards shared by the bound formulas."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np


def tiny_floor(dtype) -> float:
    """A positive floor for denominators: sqrt of the smallest normal number of ``dtype``.

    Dividing a bounded numerator by it stays finite, and so does the derivative (<= 1/floor^2 is
    not needed: the formulas that use it have derivatives bounded by ``a_max / floor``).
    """
    return float(np.sqrt(np.finfo(dtype).tiny))


def candidates(center, offsets, lo, hi):
    """Integers ``clip(center + o, lo, hi)`` for each offset, stacked on a new last axis ``(..., k)``.

    ``center`` is a float array of integer values; the result is reduced with ``min``/``max`` over
    the last axis by the caller, so every formula is written (and differentiated) once.
    """
    center = jnp.asarray(center)
    offsets = jnp.asarray(offsets, center.dtype).reshape((1,) * center.ndim + (-1,))
    return jnp.clip(center[..., None] + offsets, lo, hi)
