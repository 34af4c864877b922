"""The semi-implicit bounds against an independent brute-force reference (``semi_implicit_reference.py``).

The reference knows nothing of the library's closed forms (candidate substeps, the lines of the
discrete braking distance): for each side it bisects on the acceleration with a predicate that
runs the substeps of the step and then full braking substep by substep, and it judges viability by
summing the braking distance term by term. ``test_scalar_reference.py``'s semi-implicit port copies
the library's formulas; this is the check that does not.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(__file__))

import jaxlimits as jl  # noqa: E402
import semi_implicit_reference as sir  # noqa: E402

# (q_min, q_max, v_max, a_max), dt
CONFIGS = {
    "fig4": ((-2.0, 2.0, 2.0, 12.0), 0.01),
    "fig3": ((-0.5, 0.5, 2.0, 10.0), 0.1),
    "asym": ((-0.3, 1.7, 1.5, 20.0), 0.02),
    "edge11": ((-0.05, 0.05, 1.0, 9.998), 0.1),  # condition (11) within 0.02 % of equality
}
TOL = 1e-9  # relative to a_max
BATCH = 4096  # one array shape for every call: eager dispatch compiles each operation once


def padded_bounds(q, v, lim, dt, substeps):
    """``jl.acc_bounds`` (semi-implicit, no rounding guard) on ``BATCH`` states, the tail padded with rest states."""
    count = len(q)
    assert count <= BATCH
    pad = np.full(BATCH - count, 0.5 * (lim[0] + lim[1]))
    b = jl.acc_bounds(
        np.concatenate([q, pad]),
        np.concatenate([v, 0 * pad]),
        jl.JointLimits(*lim),
        dt,
        integrator="semi_implicit",
        substeps=substeps,
        rounding_guard=False,
    )
    return tuple(np.asarray(x)[:count] for x in b)


def boundary_states(lim, dt, n):
    """States exactly on the edges of the viable set and of the formulas' branches, both sides."""
    q_min, q_max, v_max, a_max = lim
    h = dt / n
    v = np.concatenate(
        [
            v_max * np.linspace(0.0, 1.0, 21),
            h * a_max * np.arange(1, int(v_max / (h * a_max)) + 1),  # the kinks of D(v): v = K h a_max
        ]
    )
    v = v[v <= v_max]
    D = sir.braking_distance(v, a_max, h)
    rows_q, rows_v = [], []
    for d, vv in (
        (D, v),
        (D * (1 + 1e-12), v),
        (D + 1e-9, v),
        (0 * v, -v),
        (0.5 * h * v, v),
        (h * v, v),
        (2 * h * v, v),
    ):
        rows_q += [q_max - d, q_min + d]
        rows_v += [vv, -vv]
    mid = 0.5 * (q_min + q_max)
    rows_q += [np.array([q_max, q_min, mid, mid, q_max, q_min])]
    rows_v += [np.array([0.0, 0.0, v_max, -v_max, -v_max, v_max])]
    return np.concatenate(rows_q), np.concatenate(rows_v)


def random_states(lim, count, rng):
    q_min, q_max, v_max, _ = lim
    q = rng.uniform(q_min, q_max, count)
    v = v_max * rng.uniform(-1, 1, count)
    d = (q_max - q_min) * rng.uniform(size=count) ** 3  # crowd the limits
    side = rng.choice([-1.0, 1.0], count)
    return np.concatenate([q, np.where(side > 0, q_max - d, q_min + d)]), np.concatenate([v, -side * v])


@pytest.mark.parametrize("substeps", [1, 2, 5])
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_semi_implicit_bounds_equal_brute_force(name, substeps, x64):
    lim, dt = CONFIGS[name]
    q_min, q_max, v_max, a_max = lim
    rng = np.random.default_rng(sum(map(ord, name)) + substeps)
    qb, vb = boundary_states(lim, dt, substeps)
    qr, vr = random_states(lim, 1000, rng)
    q, v = np.concatenate([qb, qr]), np.concatenate([vb, vr])
    ref_lower, ref_upper = sir.bounds(q, v, *lim, dt, substeps)
    ref_viable = sir.viable(q, v, *lim, dt, substeps)
    lower, upper, viable = padded_bounds(q, v, lim, dt, substeps)
    assert lower.dtype == np.float64
    # viability: the same set, up to states within rounding of its boundary (the two sum D(v) differently)
    h = dt / substeps
    gap = np.minimum(q_max - q - sir.braking_distance(v, a_max, h), q - q_min - sir.braking_distance(-v, a_max, h))
    disagree = viable != ref_viable
    assert np.all(np.abs(gap[disagree]) <= 1e-14 * (q_max - q_min)), gap[disagree]
    both = viable & ref_viable
    assert np.count_nonzero(both) > 0.6 * len(q) and np.count_nonzero(both[: len(qb)]) > 0.5 * len(qb)
    err = np.maximum(np.abs(lower - ref_lower), np.abs(upper - ref_upper)) / a_max
    worst = int(np.argmax(np.where(both, err, -1.0)))
    assert np.all(err[both] <= TOL), (
        q[worst],
        v[worst],
        (lower[worst], upper[worst]),
        (ref_lower[worst], ref_upper[worst]),
    )
    # and the interval is never empty there (the reference's sides are computed apart)
    assert np.all(ref_lower[both] <= ref_upper[both] + TOL * a_max)


def test_reference_braking_distance_and_predicate():
    """The reference itself on hand-checkable cases: D(v) by its definition, and the predicate's edges."""
    h, a_max = 0.01, 10.0
    # v = 0.35: terms 0.35 - 0.1 k for k = 1, 2, 3 -> 0.25 + 0.15 + 0.05 = 0.45, times h
    np.testing.assert_allclose(
        sir.braking_distance(np.array([0.35, 0.1, 0.0, -1.0]), a_max, h),
        [0.0045, 0.0, 0.0, 0.0],
        rtol=1e-12,
        atol=1e-18,
    )
    # at rest exactly on q_max: a = 0 is allowed, any positive a is not; -a_max always is
    ok = sir.upper_ok(np.array([0.0, 1e-9, -a_max]), 0.0, 0.0, 1.0, a_max, 0.05, 5)
    assert ok.tolist() == [True, False, True]
    # above a_max or past the velocity limit: never
    assert not sir.upper_ok(a_max * 1.0000001, 10.0, 0.0, 1.0, a_max, 0.05, 5)
    assert not sir.upper_ok(0.0, 10.0, 1.0000001, 1.0, a_max, 0.05, 5)
