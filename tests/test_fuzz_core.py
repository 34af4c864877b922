"""Fuzzed inputs for the core (issue 16, item 4): every case ends in an eager error naming the field and
its value, or in the documented outcome -- never a NaN handed on, never a violation, never a hang.

Entry points: ``JointLimits``, ``acc_bounds`` (``viability``, ``jerk``; zoh and semi-implicit with 1 or
5 substeps), ``solve_box_qp``/``project_box``, ``impact_speed_cap``/``impact_constraints``,
``timescale_ik``/``fixed_time_ik``. Limits are drawn log-uniformly over 1e-6 ... 1e6 and the control
period over 1e-5 ... 1 s; states at +-0, denormals, exactly at and past every limit, huge, infinite
and NaN; commands NaN, +-inf and 1e30; metrics with condition numbers up to 1e12, duplicated and
contradicting halfspaces.

Each accepted configuration is judged by the independent simulators of ``reference.py`` and
``jerk_reference.py`` (one step in the state's dtype): from a state the library calls viable, the
ends and the midpoint of the interval keep the position, velocity, acceleration (and jerk) limits as
the state's dtype represents them (tolerance 0 beyond the representation: the rounding guard is
there to absorb the update's rounding), and the next state is viable again (the induction the
guarantee rests on). Shapes are fixed (``N`` joints) and the limits and ``dt`` are jitted arguments,
so every configuration compiles once per dtype, not once per example.

The number of cases run per entry point is printed by the last test (``COUNTS``).
"""

from __future__ import annotations

import collections
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, note, settings
from hypothesis import strategies as st

import jaxlimits as jl
from jaxlimits._src.jerk_condition import jerk_condition_needs
from jerk_reference import simulate_step
from qp_reference import rows_feasible

N = 3  # joints per case: one compiled program per (family, model, dtype)
COUNTS: collections.Counter = collections.Counter()
DTYPES = [np.float32, np.float64]
MODELS = [("zoh", 1), ("semi_implicit", 1), ("semi_implicit", 5)]
SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])


def log_uniform(lo, hi):
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda x: 10.0**x)


def names_field_and_value(message: str, field: str, value) -> bool:
    """The message names the field and shows the value (as the library prints it: repr, list or ``%g``)."""
    if field not in message:
        return False
    vals = np.atleast_1d(np.asarray(value, dtype=np.float64)).ravel()
    shown = []
    for x in vals:
        if np.isnan(x):
            shown.append("nan")
        elif np.isinf(x):
            shown.append("inf")
        else:
            shown.append(None)
    if any(s is not None and s in message for s in shown):
        return True
    return any(
        any(f in message for f in (repr(float(x)), str(float(x)), f"{x:.6g}", f"{x:g}")) for x in vals if np.isfinite(x)
    )


# ------------------------------------------------------------------------------------------ JointLimits


BAD = [np.nan, np.inf, -np.inf, 0.0, -0.0, -1.0, -5e-324]
GOOD = log_uniform(1e-6, 1e6)


def field_values():
    return st.one_of(GOOD, GOOD.map(lambda x: -x), st.sampled_from(BAD), st.just(5e-324), st.just(1e308))


@given(
    st.lists(field_values(), min_size=5, max_size=5),
    st.sampled_from(["scalar", "array", "mixed", "bad_shape"]),
    st.booleans(),
)
@settings(max_examples=300, **SETTINGS)
@example([np.nan, 1.0, 1.0, 1.0, 1.0], "scalar", False)
@example([0.0, 0.0, 1.0, 1.0, 1.0], "array", False)
@example([-1.0, 1.0, 1.0, 1.0, -0.0], "scalar", True)
def test_joint_limits_reject_bad_fields_eagerly_by_name(values, shape_kind, with_jerk):
    COUNTS["JointLimits"] += 1
    q_min, q_max, v_max, a_max, j_max = values
    fields = dict(q_min=q_min, q_max=q_max, v_max=v_max, a_max=a_max, j_max=j_max if with_jerk else None)
    if shape_kind == "array":
        fields = {k: (None if x is None else np.full(N, x)) for k, x in fields.items()}
    elif shape_kind == "mixed":
        fields["v_max"] = np.array([v_max, 1.0, 2.0])
    elif shape_kind == "bad_shape":
        fields["a_max"] = np.full(N + 1, a_max)
        fields["q_max"] = np.full(N, q_max)
    try:
        lim = jl.JointLimits(**fields)
    except ValueError as exc:
        msg = str(exc)
        note(msg)
        if "shapes that do not broadcast" in msg:
            assert shape_kind == "bad_shape"
            return
        bad_finite = [k for k, x in fields.items() if x is not None and not np.all(np.isfinite(x))]
        if bad_finite:
            k = bad_finite[0]
            assert f"JointLimits.{k} must be finite" in msg and names_field_and_value(msg, k, fields[k]), msg
        elif "q_min < q_max" in msg:
            assert np.any(np.asarray(fields["q_min"]) >= np.asarray(fields["q_max"])), msg
            assert names_field_and_value(msg, "q_min", fields["q_min"]), msg
        else:
            bad = [
                k for k in ("v_max", "a_max", "j_max") if fields[k] is not None and np.any(np.asarray(fields[k]) <= 0)
            ]
            assert bad and f"JointLimits.{bad[0]} must be > 0" in msg, msg
            assert names_field_and_value(msg, bad[0], fields[bad[0]]), msg
        return
    # accepted: every documented rule holds
    assert shape_kind != "bad_shape"
    for k, x in fields.items():
        if x is not None:
            assert np.all(np.isfinite(getattr(lim, k)))
    assert np.all(lim.q_min < lim.q_max)
    assert np.all(lim.v_max > 0) and np.all(lim.a_max > 0) and (lim.j_max is None or np.all(lim.j_max > 0))


# ------------------------------------------------------------------------------------------ acc_bounds


@functools.partial(jax.jit, static_argnames=("method", "integrator", "substeps"))
def _bounds(q, v, a_prev, q_min, q_max, v_max, a_max, j_max, dt, *, method, integrator, substeps):
    """The library's bounds with the limits and ``dt`` as jitted arguments (documented: checks eager, outside)."""
    lim = jl.JointLimits(q_min, q_max, v_max, a_max, j_max if method == "jerk" else None)
    limit = jl.make_limit(method, lim, dt, integrator, substeps)
    return limit.bounds(q, v, a_prev if limit.needs_a_prev else None)


@st.composite
def kinematic_limits(draw, jerk: bool):
    """Per-joint limits and dt over 1e-6 ... 1e6 (dt 1e-5 ... 1 s), mostly near the admissible edge.

    ``a_max`` is drawn relative to what condition (11) (or the jerk condition) allows, from far
    inside to just past it (the eager check decides; exact equality fails by its 0.01 % slack).
    """
    integrator, substeps = draw(st.sampled_from(MODELS))
    dt = draw(log_uniform(1e-5, 1.0))
    span = np.array([draw(GOOD) for _ in range(N)])
    v_max = np.array([draw(GOOD) for _ in range(N)])
    where = draw(st.sampled_from(["zero", "positive", "negative", "far"]))
    if where == "zero":
        center = np.zeros(N)
    else:
        center = np.array([draw(log_uniform(1e-6, 1e6 if where == "far" else 1.0)) for _ in range(N)])
        center = -center if where == "negative" else center
    q_min = center - span * draw(st.sampled_from([0.0, 0.5, 1.0]))
    q_max = q_min + span
    edge = draw(st.sampled_from(["inside"] * 6 + ["near", "equal", "over"]))
    ratio = {"inside": log_uniform(1e-6, 1.0), "near": log_uniform(0.999, 1.001), "equal": st.just(1.0)}.get(
        edge, st.just(1.5)
    )
    ratio = draw(ratio)
    if not jerk:
        a_ok = np.minimum(span / dt**2, v_max / dt)
        return integrator, substeps, dt, q_min, q_max, v_max, a_ok * ratio, None
    a_max = np.array([draw(GOOD) for _ in range(N)])
    j_max = a_max / dt * np.array([draw(log_uniform(1e-2, 1e3)) for _ in range(N)])
    for _ in range(3):  # the needs grow with |q_max| and v_max (their rounding margin): a few rounds settle them
        lim = jl.JointLimits(q_min, q_min + span, v_max, a_max, j_max)
        span_needed, v_needed, _ = jerk_condition_needs(lim, dt, integrator, substeps)
        span = np.maximum(span, span_needed / ratio)
        v_max = np.maximum(v_max, v_needed / ratio)
    q_max = q_min + span
    return integrator, substeps, dt, q_min, q_max, v_max, a_max, j_max


def special_states(draw, dtype, q_min, q_max, v_max, a_max):
    """One state per joint: at +-0, denormal, exactly at or past a limit, on the braking curve, huge, inf, NaN."""
    tiny = float(np.finfo(dtype).smallest_subnormal)
    big = float(np.finfo(dtype).max)
    q, v, kinds = np.zeros(N), np.zeros(N), []
    for j in range(N):
        lo, hi, vm, am = q_min[j], q_max[j], v_max[j], a_max[j]
        kind = draw(
            st.sampled_from(
                ["inside", "zero", "denormal", "at_q", "at_v", "at_both", "curve", "past", "huge", "inf", "nan"]
            )
        )
        u = draw(st.floats(0.0, 1.0))
        s = draw(st.sampled_from([1.0, -1.0]))
        span = hi - lo
        if kind == "inside":
            q[j], v[j] = lo + u * span, vm * draw(st.floats(-1.0, 1.0))
        elif kind == "zero":
            q[j], v[j] = draw(st.sampled_from([0.0, -0.0])), draw(st.sampled_from([0.0, -0.0]))
        elif kind == "denormal":
            q[j] = draw(st.sampled_from([0.0, tiny, -tiny, lo + u * span]))
            v[j] = s * tiny * draw(st.sampled_from([1.0, 3.0, 2.0**20]))
        elif kind == "at_q":
            q[j], v[j] = (hi if s > 0 else lo), draw(st.sampled_from([0.0, -0.0, -s * vm * u, s * tiny]))
        elif kind == "at_v":
            q[j], v[j] = lo + u * span, s * vm
        elif kind == "at_both":
            q[j], v[j] = (hi if s > 0 else lo), draw(st.sampled_from([vm, -vm]))
        elif kind == "curve":  # zoh's curve v = sqrt(2 a_max d) (inside the semi-implicit one), the last ulps
            d = span * u**4
            v[j] = min(math.sqrt(2.0 * am * d), vm)
            q[j] = hi - d if s > 0 else lo + d
            v[j] *= s
        elif kind == "past":
            past = span * draw(log_uniform(1e-12, 10.0))
            q[j] = hi + past if s > 0 else lo - past
            v[j] = vm * draw(st.floats(-1.5, 1.5))
        elif kind == "huge":
            q[j], v[j] = draw(st.sampled_from([(1e30, 0.0), (0.0, 1e30), (big, -big), (-1e30, 1e30)]))
        elif kind == "inf":
            q[j], v[j] = draw(st.sampled_from([(np.inf, 0.0), (0.0, -np.inf), (-np.inf, np.inf)]))
        else:
            q[j], v[j] = draw(st.sampled_from([(np.nan, 0.0), (0.0, np.nan), (lo, np.nan)]))
        kinds.append(kind)
    with np.errstate(over="ignore"):
        return q.astype(dtype), v.astype(dtype), kinds


def simulate(q, v, a, dt, integrator, substeps, dtype):
    """One step by the reference simulators, the end state rounded as a ``dtype`` simulator would."""
    out = simulate_step(q, v, a, dt, integrator, substeps, dtype)
    return tuple(np.asarray(x) for x in out)


def check_step_from_viable(name, dtype, cfg, q, v, a_prev, b, viable, inner, method):
    """From each state the library calls viable: one simulated step at lower, upper and midpoint keeps every
    limit as ``dtype`` represents it (to a few roundings for states in the band between the guarded and the
    exact kernel), and, from the guarded kernel, the library calls the next state viable again."""
    integrator, substeps, dt, q_min, q_max, v_max, a_max, j_max = cfg
    lim = [np.asarray(x, dtype).astype(np.float64) for x in (q_min, q_max, v_max, a_max)]
    # one unit of roundoff of the limits' magnitude (the state is rounded at that scale; a denormal speed
    # at a limit reads as viable because v^2 underflows, and then moves ~|v| T past it)
    eps = float(np.finfo(dtype).eps)
    tol_q = eps * np.maximum(np.abs(lim[0]), np.abs(lim[1]))
    tol_v = eps * lim[2]
    # a viable state outside the guarded kernel (on the exact boundary: e.g. at v_max on q_min, reaching q_max in
    # one step) is beyond what the rounding guard covers: its step may end a few roundings past the limit (the
    # issue's float64 jerk rollout from exactly v_max: 4e-16 over); 8 roundings of the step's scale |q| + |v| dt
    band = viable & ~inner
    tol_q = np.where(band, 8.0 * eps * (np.maximum(np.abs(lim[0]), np.abs(lim[1])) + lim[2] * dt), tol_q)
    tol_v = np.where(band, 8.0 * eps * (lim[2] + lim[3] * dt), tol_v)
    lower, upper = (np.asarray(x) for x in (b.lower, b.upper))
    for a in (lower, upper, (0.5 * (lower.astype(np.float64) + upper)).astype(dtype)):
        with np.errstate(all="ignore"):  # (the non-viable joints' huge states overflow; they are not judged)
            q1, v1, q_lo, q_hi = simulate(q, v, a, dt, integrator, substeps, dtype)
            q1, v1 = q1.astype(dtype), v1.astype(dtype)
            excess = np.where(viable, np.maximum(lim[0] - q_lo, q_hi - lim[1]) / tol_q, -np.inf)
        ok = viable
        # (the interval's ends are in dtype; the reference's in-step extremes are float64 of dtype values)
        COUNTS["acc_bounds: worst position excess / tolerance"] = max(
            COUNTS["acc_bounds: worst position excess / tolerance"],
            float(np.max(excess)),
        )
        assert np.all(np.where(ok, q_lo >= lim[0] - tol_q, True)), (name, q, v, a, q_lo, lim[0])
        assert np.all(np.where(ok, q_hi <= lim[1] + tol_q, True)), (name, q, v, a, q_hi, lim[1])
        assert np.all(np.where(ok, np.abs(v1) <= lim[2] + tol_v, True)), (name, q, v, a, v1, lim[2])
        assert np.all(np.where(ok, np.abs(a) <= lim[3], True)), (name, a, lim[3])
        if method == "jerk":
            step = (np.asarray(j_max) * dt).astype(dtype)
            jerk = np.abs(a.astype(np.float64) - a_prev.astype(np.float64))
            # |a - a_prev| <= j_max dt, to the rounding of the two accelerations compared
            slack = np.spacing(np.maximum(np.abs(a), np.abs(a_prev)).astype(dtype)).astype(np.float64)
            assert np.all(np.where(ok, jerk <= step + slack, True)), (name, a, a_prev, step)
        nxt = _bounds(
            q1, v1, a.astype(dtype), *(np.asarray(x, dtype) for x in (q_min, q_max, v_max, a_max)),
            np.asarray(1.0 if j_max is None else j_max, dtype), dtype(dt),
            method=method, integrator=integrator, substeps=substeps,
        )  # fmt: skip
        ok = inner
        assert np.all(np.where(ok, np.asarray(nxt.viable), True)), (name, q, v, a, q1, v1, "next state not viable")


def guard_fits(dtype, cfg, method):
    """Whether the documented rounding guard (``acc_bounds``: ``R eps (max|q_lim| + 2 v^2 / a_max)`` per
    limit, ``R = 2 + r (1 + stop_steps)``) leaves some range: the position part ``R eps max|q_lim|`` alone,
    with ``v`` capped by the range (the speed term is what the library caps; the magnitude term it cannot)."""
    integrator, substeps, dt, q_min, q_max, v_max, a_max, j_max = cfg
    if method == "jerk":  # check_jerk_condition already demands the range hold the jerk guard
        return np.ones(N, bool)
    r = 3 if integrator == "zoh" else substeps
    v_reach = np.minimum(v_max, np.sqrt(2.0 * a_max * (q_max - q_min)) + a_max * dt)
    R = 2.0 + r * (1.0 + np.ceil(v_reach / (a_max * dt)))
    m_q = R * np.finfo(dtype).eps * (np.maximum(np.abs(q_min), np.abs(q_max)) + 2.0 * v_reach**2 / a_max)
    return 2.0 * m_q < q_max - q_min


def guarded_limits(dtype, cfg, method):
    """The limits narrowed by twice the documented rounding guard: states viable for these are inside the
    guarded kernel, from where the next state must be viable again (between the guarded and the exact
    kernel the bounds are the best effort, and one rounding may carry a state riding the exact curve out)."""
    integrator, substeps, dt, q_min, q_max, v_max, a_max, j_max = cfg
    r = 3 if integrator == "zoh" else substeps
    v_reach = np.minimum(v_max, np.sqrt(2.0 * a_max * (q_max - q_min)) + a_max * dt)
    steps = np.ceil(v_reach / (a_max * dt))
    if method == "jerk":
        r, v_reach, steps = r + 2, v_max, np.ceil(v_max / (a_max * dt)) + np.ceil(3.0 * a_max / (j_max * dt)) + 1.0
    R = 2.0 * (2.0 + r * (1.0 + steps)) * np.finfo(dtype).eps
    m_q = R * (np.maximum(np.abs(q_min), np.abs(q_max)) + 2.0 * v_reach**2 / a_max)
    return q_min + m_q, q_max - m_q, v_max * (1.0 - R)


def run_bounds_case(method, dtype, data):
    cfg = data.draw(kinematic_limits(jerk=method == "jerk"), label="config")
    integrator, substeps, dt, q_min, q_max, v_max, a_max, j_max = cfg
    key = f"acc_bounds[{method}]"
    COUNTS[key] += 1
    try:
        limits = jl.JointLimits(q_min, q_max, v_max, a_max, j_max)
        jl.make_limit(method, limits, dt, integrator, substeps)  # every configuration check is eager
    except ValueError as exc:
        msg = str(exc)
        note(msg)
        COUNTS[key + " eager error"] += 1
        if method == "viability":
            assert "condition (11)" in msg and names_field_and_value(msg, "a_max", a_max), msg
            assert f"dt={dt}" in msg
        else:
            assert "check_jerk_condition" in msg and ("q_max - q_min" in msg or "v_max" in msg), msg
            assert f"dt={dt!r}" in msg and "a_max=" in msg and "j_max=" in msg, msg
        return
    q, v, kinds = special_states(data.draw, dtype, q_min, q_max, v_max, a_max)
    note(f"kinds={kinds} q={q.tolist()} v={v.tolist()}")
    if method == "jerk":
        a_prev = np.array([data.draw(st.floats(-1.0, 1.0)) for _ in range(N)]) * a_max
        a_prev = np.where(data.draw(st.booleans()), 0.0, a_prev).astype(dtype)
    else:
        a_prev = np.zeros(N, dtype)
    args = [np.asarray(x, dtype) for x in (q_min, q_max, v_max, a_max, 1.0 if j_max is None else j_max)]
    b = _bounds(q, v, a_prev, *args, dtype(dt), method=method, integrator=integrator, substeps=substeps)
    lower, upper, viable = (np.asarray(x) for x in b)
    assert lower.dtype == dtype and viable.dtype == np.bool_
    finite_state = np.isfinite(q) & np.isfinite(v) & np.isfinite(a_prev)
    # a non-finite state is never viable
    assert not np.any(viable & ~finite_state), (kinds, viable)
    COUNTS[key + " non-finite state"] += int(not np.all(finite_state))
    # documented: -a_max <= lower <= upper <= a_max (finite), and lower = upper = 0 for a NaN state
    amax = np.asarray(a_max, dtype)
    nan = np.isnan(q) | np.isnan(v) | (np.isnan(a_prev) if method == "jerk" else False)
    assert np.all(np.isfinite(lower)) and np.all(np.isfinite(upper)), (kinds, lower, upper)
    assert np.all(lower <= upper), (kinds, lower, upper)
    assert np.all(-amax <= lower) and np.all(upper <= amax), (kinds, lower, upper, amax)
    assert np.all(lower[nan] == 0.0) and np.all(upper[nan] == 0.0), (kinds, lower, upper)
    # where the float32 rounding guard is wider than half the range (limits far from 0 relative to their
    # range) the guarded limits meet at the midpoint (test_guard_wider_than_the_range_meets_at_the_midpoint);
    # the guard then covers no rounding, so such joints are only checked for order and finiteness
    fits = guard_fits(dtype, cfg, method)
    COUNTS[key + " joints whose guard does not fit the range"] += int(np.sum(~fits))
    viable = viable & fits
    COUNTS[key + " viable joints"] += int(np.sum(viable))
    if np.any(viable):
        g_lo, g_hi, g_v = guarded_limits(dtype, cfg, method)
        inner = _bounds(
            q, v, a_prev, *(np.asarray(x, dtype) for x in (g_lo, np.maximum(g_hi, g_lo), g_v)), args[3], args[4],
            dtype(dt), method=method, integrator=integrator, substeps=substeps,
        ).viable  # fmt: skip
        inner = np.asarray(inner) & viable & (g_lo < g_hi)
        COUNTS[key + " viable joints in the guard band"] += int(np.sum(viable & ~inner))
        check_step_from_viable(key, dtype, cfg, q, v, a_prev, b, viable, inner, method)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@given(data=st.data())
@settings(max_examples=150, **SETTINGS)
def test_viability_bounds_fuzzed(dtype, data):
    with jax.enable_x64(dtype == np.float64):
        run_bounds_case("viability", dtype, data)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@given(data=st.data())
@settings(max_examples=100, **SETTINGS)
def test_jerk_bounds_fuzzed(dtype, data):
    with jax.enable_x64(dtype == np.float64):
        run_bounds_case("jerk", dtype, data)


def test_guard_wider_than_the_range_meets_at_the_midpoint():
    """Found by fuzzing (float32): limits [1000, 1000.01], v_max 1, a_max 1e-4, dt 1 s -- accepted by condition
    (11); the rounding guard (50 roundings of eps * 1000 per limit) is wider than half the range, the guarded
    limits crossed, and a joint at rest exactly on q_max was told to accelerate upward (lower = upper = +a_max).
    Now the guarded limits meet at the midpoint: the joint brakes toward it."""
    lim = jl.JointLimits(1000.0, 1000.01, 1.0, 1e-4)
    jl.make_limit("viability", lim, 1.0)  # accepted eagerly
    b = jl.acc_bounds(jnp.float32(1000.01), jnp.float32(0.0), lim, 1.0)
    assert bool(b.viable)
    assert float(b.upper) <= 0.0, b  # at rest on q_max: no upward acceleration is safe


@pytest.mark.parametrize("method", ["naive", "viability", "jerk"])
def test_nan_state_gets_zero_bounds(method):
    """Found by fuzzing: a NaN ``q``, ``v`` (or ``a_prev`` for ``jerk``) gave ``viable=False`` and NaN bounds
    (every family, both dtypes), so a command projected into them was NaN. Documented outcome now (``Bounds``):
    no side to brake toward, ``lower = upper = 0``, not viable; the other joints are unaffected."""
    lim = jl.JointLimits(-2.0, 2.0, 2.0, 12.0, j_max=2000.0)
    q, v, a_prev = jnp.array([np.nan, 0.0, 0.0]), jnp.array([0.0, np.nan, 0.0]), jnp.array([0.0, 0.0, np.nan])
    kw = {"a_prev": a_prev} if method == "jerk" else {}
    b = jl.acc_bounds(q, v, lim, 0.01, method=method, **kw)
    bad = 3 if method == "jerk" else 2
    assert not np.any(np.asarray(b.viable)[:bad]), b
    assert np.all(np.asarray(b.lower)[:bad] == 0.0) and np.all(np.asarray(b.upper)[:bad] == 0.0), b
    if method != "jerk":
        ok = jl.acc_bounds(jnp.zeros(3), jnp.zeros(3), lim, 0.01, method=method)
        assert bool(b.viable[2]) and float(b.lower[2]) == float(ok.lower[2]) and float(b.upper[2]) == float(ok.upper[2])


# ------------------------------------------------------------------------------------------ box QP

M_ROWS = 4


@st.composite
def qp_problems(draw, dtype):
    """n = 3, 4 rows: random, duplicated, contradicting (a row and its negation past it), zero, far; metric of
    condition 1 ... 1e12 at scale 1e-6 ... 1e6; x_des inside, outside, on the box; degenerate boxes."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    lo = rng.uniform(-2.0, 0.0, N) * draw(GOOD)
    hi = lo + rng.uniform(0.0, 2.0, N) * draw(st.sampled_from([0.0, 1.0, 1e-6, 1e6]))
    cond = draw(log_uniform(1.0, 1e12))
    Q, _ = np.linalg.qr(rng.normal(size=(N, N)))
    eig = np.exp(rng.uniform(0.0, np.log(cond), N))
    eig[0], eig[-1] = 1.0, cond
    W = Q @ np.diag(eig) @ Q.T * draw(GOOD) / cond**0.5
    W = 0.5 * (W + W.T)
    x_des = rng.uniform(-4.0, 4.0, N) * np.maximum(np.abs(lo), np.abs(hi)).max()
    for j in range(N):  # (1e30 and +-inf commands: test_extreme_commands)
        x_des[j] = draw(st.sampled_from([x_des[j], x_des[j], lo[j], hi[j]]))
    G, h = rng.normal(size=(M_ROWS, N)), rng.normal(size=M_ROWS)
    for i in range(1, M_ROWS):
        kind = draw(st.sampled_from(["random", "duplicate", "contradict", "zero", "far"]))
        if kind == "duplicate":
            G[i], h[i] = G[i - 1], h[i - 1]
        elif kind == "contradict":
            G[i], h[i] = -G[i - 1], -h[i - 1] - draw(st.sampled_from([0.0, 1e-9, 1.0, 1e6]))
        elif kind == "zero":
            G[i], h[i] = 0.0, draw(st.sampled_from([0.0, 1.0, -1.0]))
        elif kind == "far":
            h[i] = draw(st.sampled_from([1e6, 1e30]))
    rows = draw(st.booleans())
    with np.errstate(over="ignore"):
        cast = [np.asarray(x, dtype) for x in (x_des, lo, hi, W, G, h)]
    return cast + [rows, cond]


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
@given(data=st.data())
@settings(max_examples=60, **SETTINGS)
def test_box_qp_fuzzed(dtype, data):
    """Either an eager ``ValueError`` naming ``metric`` (or ``h``/``G``: non-finite after the cast to the
    dtype) with its value, or: ``x`` finite and in the box exactly; without ``infeasible`` every row holds to
    the rounding of ``|G| (|x| + |x_des|) + |h|`` times the metric's condition number beyond ``1/eps``; ``infeasible`` only when SciPy's LP finds the rows infeasible on the box
    (checked unless the rows are within rounding of feasible); ``violation`` is what ``x`` shows."""
    with jax.enable_x64(dtype == np.float64):
        x_des, lo, hi, W, G, h, rows, cond = data.draw(qp_problems(dtype))
        COUNTS["solve_box_qp"] += 1
        kw = dict(G=G, h=h) if rows else {}
        try:
            res = jl.solve_box_qp(x_des, lo, hi, W, **kw)
        except ValueError as exc:
            msg = str(exc)
            note(msg)
            COUNTS["solve_box_qp eager error"] += 1
            assert msg.startswith("project_box: "), msg
            assert "metric" in msg or "h must be finite" in msg or "G must be finite" in msg, msg
            if "positive definite" in msg:  # the smallest eigenvalue is named
                assert "smallest eigenvalue" in msg
            return
        x = np.asarray(res.x).astype(np.float64)
        assert np.all(np.isfinite(x)), (x, x_des)
        assert np.all(x >= lo) and np.all(x <= hi), (x, lo, hi)
        if not rows:
            return
        eps = float(np.finfo(dtype).eps)
        G64, h64 = G.astype(np.float64), h.astype(np.float64)
        # the solver works with W (x - x_des): its rounding is at the scale of x_des too
        scale = np.abs(G64) @ (np.abs(x) + np.abs(x_des.astype(np.float64))) + np.abs(h64)
        # rounding of each row times the conditioning the solver works at (the metric's and the rows' own)
        tol = 64 * N * eps * scale * max(1.0, cond * eps)
        r = G64 @ x - h64
        feasible = rows_feasible(lo.astype(np.float64), hi.astype(np.float64), G64, h64)
        if not bool(res.infeasible):
            COUNTS["solve_box_qp feasible"] += 1
            assert np.all(r <= tol), (r, tol)
        else:
            COUNTS["solve_box_qp flagged infeasible"] += 1
            # never flagged for rows a box point meets with room to spare
            relaxed = rows_feasible(lo.astype(np.float64), hi.astype(np.float64), G64, h64 - tol)
            assert not relaxed, ("flagged infeasible but feasible", r, tol)
        note(f"feasible(LP)={feasible}")
        assert abs(float(res.violation) - max(0.0, float(np.max(r)))) <= np.max(tol) + 1e-300


def test_extreme_commands():
    """Commands 1e30 and +-inf: the clip maps them to the box; the dense metric keeps the box and the rows for
    1e30 (float32 and float64)."""
    W = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]])
    G, h = np.array([[1.0, 1.0, 1.0]]), np.array([0.5])
    for dtype in DTYPES:
        with jax.enable_x64(dtype == np.float64):
            for big in (1e30, -1e30, np.inf, -np.inf):
                COUNTS["solve_box_qp extreme command"] += 1
                x = np.asarray(jl.project_box(np.array([big, 0.0, 0.0], dtype), -1.0, 1.0))
                assert x[0] == np.sign(big) and np.all(np.isfinite(x))
                if np.isfinite(big):
                    r = jl.solve_box_qp(np.array([big, 0.0, 0.0], dtype), -1.0, 1.0, W.astype(dtype), G=G, h=h)
                    x = np.asarray(r.x)
                    assert np.all(np.isfinite(x)) and np.all(np.abs(x) <= 1.0) and G[0] @ x <= h[0] + 1e-6


def test_infinite_command_with_a_dense_metric_is_not_converged():
    """Found by fuzzing: ``solve_box_qp([0, inf, 0], -1, 1, W)`` with a dense SPD ``W`` returns NaN, and said
    ``converged=True``. Documented outcome now: a non-finite command is not a finite input; ``converged`` is
    False for it (the shields substitute braking before projecting: tests/test_nonfinite_guard.py)."""
    W = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]], np.float32)
    r = jl.solve_box_qp(np.array([0.0, np.inf, 0.0], np.float32), -1.0, 1.0, W)
    assert not bool(r.converged), r
    r = jl.solve_box_qp(np.array([[0.0, np.inf, 0.0], [0.0, 3.0, 0.0]], np.float32), -1.0, 1.0, W)
    assert np.asarray(r.converged).tolist() == [False, True] and np.all(np.isfinite(np.asarray(r.x)[1]))


def test_nan_command_is_not_projected():
    """Finding (issue 16), documented limit: ``solve_box_qp`` promises ``x`` in the box "always" and "never NaN
    for finite inputs"; a NaN command is not finite input, is not refused eagerly, and comes back NaN (clip and
    dense) with ``converged=True``. The shields replace non-finite commands before projecting (their tests)."""
    COUNTS["solve_box_qp NaN command"] += 2
    x = jl.project_box(jnp.array([np.nan, 0.0, 0.0]), -1.0, 1.0)
    assert np.isnan(np.asarray(x)[0])
    r = jl.solve_box_qp(jnp.array([np.nan, 0.0, 0.0]), -1.0, 1.0, jnp.eye(3))
    assert np.all(np.isnan(np.asarray(r.x))) and not bool(r.converged)


# ------------------------------------------------------------------------------------------ impact caps


def scalar_or_bad(good):
    return st.one_of(good, good, good, good, good, st.sampled_from([np.nan, np.inf, -1.0, 0.0, 2.0]))


@given(data=st.data())
@settings(max_examples=100, **SETTINGS)
def test_impact_speed_cap_fuzzed(data):
    """Either an eager ``ValueError`` naming the bad field (``c_max``, ``dt_impact``, ``dt``, ``tau_imp_max``,
    ``M``, ``J``, ``normal``) and its value, or a cap that is finite and >= 0 in every family, 0 for a family
    whose bound the state already breaks, and at which the predicted jumps keep (16), (17), (20)."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
        L = rng.normal(size=(N, N))
        cond = data.draw(log_uniform(1.0, 1e12))
        M = L @ L.T + np.eye(N) / cond * data.draw(GOOD)
        J = rng.normal(size=(3, N)) * data.draw(st.sampled_from([1.0, 0.0, 1e-6, 1e6]))
        J[2] = data.draw(st.sampled_from([J[2], J[1], 0.0 * J[2]]))  # rank-deficient contact Jacobians too
        bad = data.draw(st.sampled_from([None] * 6 + ["tau_imp_max", "dt", "c_max", "dt_impact", "normal", "M", "J"]))
        if bad == "M":
            M[0, 0] = data.draw(st.sampled_from([np.nan, np.inf]))
        if bad == "J":
            J[1, 1] = np.nan
        normal = rng.normal(size=3)
        normal = normal / np.linalg.norm(normal) * (data.draw(st.sampled_from([2.0, 0.0])) if bad == "normal" else 1.0)
        lim = jl.JointLimits(-np.ones(N), np.ones(N), np.full(N, 2.0), np.full(N, 10.0))
        q = rng.uniform(-1.2, 1.2, N) * data.draw(st.sampled_from([1.0, 0.0, -0.0]))
        v = rng.uniform(-2.5, 2.5, N)
        fields = dict(
            tau_imp_max=data.draw(GOOD),
            dt=data.draw(log_uniform(1e-5, 1.0)),
            c_max=data.draw(st.floats(0.0, 1.0)),
            dt_impact=data.draw(log_uniform(1e-5, 1.0)),
        )
        if bad in fields:
            fields[bad] = data.draw(st.sampled_from([np.nan, np.inf, -1.0, 0.0, 2.0]))
        COUNTS["impact_speed_cap"] += 1
        try:
            cap = jl.impact_speed_cap(M, J, normal, q, v, lim, fields["tau_imp_max"], fields["dt"],
                                      fields["c_max"], fields["dt_impact"])  # fmt: skip
        except ValueError as exc:
            msg = str(exc)
            note(msg)
            COUNTS["impact_speed_cap eager error"] += 1
            bad = [k for k, x in fields.items() if not np.isfinite(x) or x < 0 or (x == 0 and k != "c_max")]
            bad += [k for k, x in fields.items() if k == "c_max" and x > 1]
            bad += ["normal"] if abs(np.linalg.norm(normal) - 1.0) > 1e-3 else []
            bad += [k for k, x in (("M", M), ("J", J)) if not np.all(np.isfinite(x))]
            assert bad and any(f"{k} must" in msg for k in bad), (bad, msg)
            return
        bad_config = [k for k, x in fields.items() if not np.isfinite(x) or x < 0 or (x == 0 and k != "c_max")]
        assert not bad_config and np.isfinite(M).all() and np.isfinite(J).all(), ("silently accepted", fields)
        caps = np.array([float(c) for c in cap])
        assert np.all(np.isfinite(caps)) and np.all(caps >= 0.0), caps
        jump = jl.impact_jump(M, J, normal, v, fields["c_max"], fields["dt_impact"])
        w = caps[0]
        dq, dtau = np.asarray(jump.dq_dw) * w, np.asarray(jump.dtau_dw) * w
        inside = np.all(np.abs(q) <= 1.0) and np.all(np.abs(v) <= 2.0)
        if inside and w < 1e300:
            tol = 1e-9 * (1.0 + np.abs(dq) + np.abs(dtau))
            dt = fields["dt"]
            assert np.all(np.abs(q + dt * dq) <= 1.0 + dt * tol), (q, dq, w)
            assert np.all(np.abs(v + dq) <= 2.0 + tol), (v, dq, w)
            assert np.all(np.abs(dtau) <= fields["tau_imp_max"] + tol), (dtau, w)
        # a bound already broken at w = 0 on the side its jump moves toward: that family's cap is 0 (the
        # docstring says so for any broken bound: test_cap_of_a_state_outside_its_limits)
        slope = np.asarray(jump.dq_dw)
        if np.any(((v > 2.0) & (slope > 0)) | ((v < -2.0) & (slope < 0))):
            assert caps[2] == 0.0
        if np.any(((q > 1.0) & (slope > 0)) | ((q < -1.0) & (slope < 0))):
            assert caps[1] == 0.0
        COUNTS["impact_speed_cap state outside, jump away: cap > 0"] += int(
            (np.any(np.abs(q) > 1.0) and caps[1] > 0) or (np.any(np.abs(v) > 2.0) and caps[2] > 0)
        )


def test_cap_of_a_state_outside_its_limits():
    """Found by fuzzing: ``impact_speed_cap``'s docstring says "A bound already violated at w = 0 (state outside
    its limits) gives a cap of 0 for that family"; a joint past ``q_max`` whose jump would move it back down got
    a positive position cap (the room was taken on the side the jump goes), so the cap's jumps did not satisfy
    (16) for that joint. The rule now follows the docstring."""
    lim = jl.JointLimits(-np.ones(N), np.ones(N), np.full(N, 2.0), np.full(N, 10.0))
    q = np.array([1.5, 0.0, 0.0])  # joint 0 past q_max = 1
    cap = jl.impact_speed_cap(np.eye(N), np.eye(N), np.array([1.0, 0.0, 0.0]), q, np.zeros(N), lim, 10.0, 0.01,
                              0.0, 0.005)  # fmt: skip
    assert float(cap.position) == 0.0, cap


# ------------------------------------------------------------------------------------------ time-scaled IK


@given(data=st.data())
@settings(max_examples=60, **SETTINGS)
def test_timescale_ik_fuzzed(data):
    """Either an eager ``ValueError`` naming the field (non-finite ``J``/``dr``, non-positive limits), or a finite
    ``(dq, t)`` keeping ``|dq| <= v_max t``, ``t >= t_min`` and ``dq_min <= dq <= dq_max``; ``reached`` only where
    ``J dq = dr`` holds. Singular and zero Jacobians, zero and huge displacements, blocked position limits."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
        J = rng.normal(size=(2, 4)) * data.draw(st.sampled_from([1.0, 1e-6, 1e6]))
        J[1] = data.draw(st.sampled_from([J[1], J[0], 0.0 * J[1]]))
        dr = rng.normal(size=2) * data.draw(st.sampled_from([1.0, 0.0, 1e-6, 1e6]))
        if data.draw(st.integers(0, 9)) == 0:
            dr[0] = data.draw(st.sampled_from([np.nan, np.inf]))
        v_max = data.draw(scalar_or_bad(GOOD))
        t_min = data.draw(scalar_or_bad(log_uniform(1e-5, 1.0)))
        width = data.draw(st.sampled_from([1e-6, 1.0, 1e6]))
        dq_min, dq_max = -rng.uniform(0, 1, 4) * width, rng.uniform(0, 1, 4) * width
        fixed = False  # (fixed_time_ik shares the checks and the solver; its compilation would double the cost)
        COUNTS["fixed_time_ik" if fixed else "timescale_ik"] += 1
        try:
            if fixed:
                res = jl.fixed_time_ik(J, dr, t_min, v_max, dq_min=dq_min, dq_max=dq_max)
            else:
                res = jl.timescale_ik(J, dr, v_max, t_min=t_min, dq_min=dq_min, dq_max=dq_max)
        except ValueError as exc:
            msg = str(exc)
            note(msg)
            COUNTS["time-scaled IK eager error"] += 1
            named = [k for k, x in (("v_max", v_max), ("t" if fixed else "t_min", t_min), ("dr", dr))
                     if not np.all(np.isfinite(x)) or (k != "dr" and x <= 0)]  # fmt: skip
            assert named and any(f"{k} must" in msg for k in named), (named, msg)
            return
        assert np.isfinite(v_max) and v_max > 0 and np.isfinite(t_min) and t_min > 0 and np.all(np.isfinite(dr))
        dq, t = np.asarray(res.dq), float(res.t)
        assert np.all(np.isfinite(dq)) and np.isfinite(t) and t > 0, res
        assert np.all(dq >= dq_min) and np.all(dq <= dq_max), (dq, dq_min, dq_max)
        if not fixed:
            eps = np.finfo(np.float64).eps
            assert t >= t_min * (1 - 4 * eps), (t, t_min)
            assert np.all(np.abs(dq) <= v_max * t * (1 + 64 * eps)), (dq, v_max, t)
        if bool(res.reached):
            scale = np.linalg.norm(J) * np.linalg.norm(dq) + np.linalg.norm(dr)
            assert np.linalg.norm(J @ dq - dr) <= 100 * np.finfo(np.float64).eps * scale + 1e-300


# ------------------------------------------------------------------------------------------ report


def test_zz_report_cases_per_entry_point(capsys):
    """Prints how many fuzzed cases each entry point ran (the module's tests run first, in file order)."""
    with capsys.disabled():
        print("\nfuzzed cases per entry point (tests/test_fuzz_core.py):")
        for key in sorted(COUNTS):
            print(f"  {key}: {COUNTS[key]}")
