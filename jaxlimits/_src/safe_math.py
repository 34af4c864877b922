"""Small numerical guards shared by the bound formulas."""

from __future__ import annotations

import numpy as np


def tiny_floor(dtype) -> float:
    """A positive floor for denominators: sqrt of the smallest normal number of ``dtype``.

    Dividing a bounded numerator by it stays finite, and so does the derivative (<= 1/floor^2 is
    not needed: the formulas that use it have derivatives bounded by ``a_max / floor``).
    """
    return float(np.sqrt(np.finfo(dtype).tiny))


def materialize(x):
    """``x`` unchanged (``x / (1 + 0 x)``, exact for finite ``x``), computed in one loop and stored once.

    XLA's CPU fusion copies a chain of cheap operations into every consumer (e.g. both output bounds
    reading both sides) and cuts it, storing an intermediate array, at every expensive operation
    (division, square root) it would have to copy: ~60 loops instead of 4, 10-20x slower for the jerk
    bounds. A chain that ends in an expensive operation is not copied: it becomes one loop.
    ``lax.optimization_barrier`` does not do this on the CPU (it is removed before fusion), and XLA
    does not fold ``0 * x`` for floats.
    """
    return x / (1.0 + 0.0 * x)
