"""An independent reference for the semi-implicit (MuJoCo/MJX Euler) bounds, by brute force.

Nothing here uses jaxlimits, its closed forms or its braking distance: every quantity is obtained
by running the substep recursion ``v += h a; q += h v`` itself (plain NumPy, float64, vectorised
over states). One control step of length ``T`` is ``n`` substeps of ``h = T / n``.

* ``braking_distance(v, a_max, h)``: ``D(v) = h sum_{k >= 1} max(v - k h a_max, 0)``, summed term
  by term (the highest point of full braking, substep by substep).
* ``upper_ok(a, d, v, ...)``: whether holding ``a`` for the next step keeps the upper-side limits
  for ever after: ``a <= a_max``, the position at every substep of the step ``<= q_max``
  (``d = q_max - q``), the velocity at the end of the step ``<= v_max`` (inside the step it is
  monotone, so its ends are its extremes), and then full braking ``a = -a_max``, substep by
  substep until the velocity is ``<= 0``, never above ``q_max``. Full braking is the pointwise
  lowest future, so this is the exact upper-side condition, and it is monotone in ``a`` (a
  down-set): a larger ``a`` gives pointwise larger velocities and positions.
* ``upper_bound``: the largest such ``a`` in ``[-a_max, a_max]`` by bisection (``-a_max`` where
  none passes: the best effort); ``bounds`` takes the lower side by the mirror image
  ``lower(q, v) = -upper(q' = -q, v' = -v)`` with the limits swapped.
"""

from __future__ import annotations

import numpy as np

BISECTIONS = 64


def braking_distance(v, a_max, h):
    """``D(v)`` for an array of velocities: the peak travel of full braking, summed substep by substep."""
    v = np.maximum(np.asarray(v, np.float64), 0.0)
    total = np.zeros_like(v)
    k = 1
    while True:
        term = np.maximum(v - k * h * a_max, 0.0)
        if not np.any(term > 0):
            return h * total
        total = total + term
        k += 1


def upper_ok(a, d, v, v_max, a_max, T, n):
    """Vectorised predicate: holding ``a`` now keeps every upper-side limit now and for ever after."""
    a, d, v = np.broadcast_arrays(*(np.asarray(x, np.float64) for x in (a, d, v)))
    h = T / n
    ok = (a <= a_max) & (a >= -a_max)
    travel, vk = np.zeros_like(v), v.copy()
    for _ in range(n):
        vk = vk + h * a
        travel = travel + h * vk
        ok &= travel <= d
    ok &= vk <= v_max
    for _ in range(int(np.ceil((v_max + a_max * T) / (a_max * h))) + 4):
        moving = vk > 0
        if not np.any(moving & ok):
            return ok
        vk = np.where(moving, vk - h * a_max, vk)
        travel = np.where(moving, travel + h * vk, travel)
        ok &= travel <= d
    raise AssertionError("full braking did not stop within its bound on the number of substeps")


def upper_bound(d, v, v_max, a_max, T, n, bisections=BISECTIONS):
    """The largest ``a`` in ``[-a_max, a_max]`` with ``upper_ok``; ``-a_max`` where none passes."""
    d, v = np.broadcast_arrays(np.asarray(d, np.float64), np.asarray(v, np.float64))
    good = np.full(d.shape, -a_max)
    bad = np.full(d.shape, a_max)
    top = upper_ok(bad, d, v, v_max, a_max, T, n)
    for _ in range(bisections):
        mid = 0.5 * (good + bad)
        passed = upper_ok(mid, d, v, v_max, a_max, T, n)
        good, bad = np.where(passed, mid, good), np.where(passed, bad, mid)
    return np.where(top, a_max, good)


def bounds(q, v, q_min, q_max, v_max, a_max, T, n):
    """``(lower, upper)`` of the next acceleration, each side by bisection on its own predicate."""
    q, v = np.asarray(q, np.float64), np.asarray(v, np.float64)
    upper = upper_bound(q_max - q, v, v_max, a_max, T, n)
    lower = -upper_bound(q - q_min, -v, v_max, a_max, T, n)
    return lower, upper


def viable(q, v, q_min, q_max, v_max, a_max, T, n):
    """Membership of the viability kernel: inside the limits and full braking stops inside on both sides."""
    q, v = np.asarray(q, np.float64), np.asarray(v, np.float64)
    h = T / n
    return (
        (q >= q_min)
        & (q <= q_max)
        & (np.abs(v) <= v_max)
        & (braking_distance(v, a_max, h) <= q_max - q)
        & (braking_distance(-v, a_max, h) <= q - q_min)
    )
