"""Impact-aware joint bounds (Wang & Kheddar, RSS 2019): predicted jumps, constraints, speed cap.

A point contact with Jacobian ``J`` (3, n) hits a wall whose normal ``n̂`` is known. ``n̂`` is the
*strike direction* (unit, pointing from the robot into the wall), so the contact-normal velocity
``w = n̂ . J v`` is positive while approaching. The discrete impact model (eqs. 2-6, 19, 22):

    A      = J M^-1 J^T,   M_eq = A^-1                                  (6)  equivalent mass
    dp     = -(1 + c) n̂ n̂^T J v                                          (4)  contact-velocity jump
    f_bar  = M_eq dp / dt_imp                                           (5)  average impulsive force
    dq     = M^-1 J^T M_eq dp = -(1 + c) w u,   u   = M^-1 J^T M_eq n̂   (22) joint-velocity jump
    dtau   = M dq / dt_imp    = -(1 + c) w t / dt_imp,  t = J^T M_eq n̂   (19) impulsive joint torque

Every jump is linear in ``w``; the worst case of the restitution range ``[c_min, c_max]`` is
``c_max`` (the jumps grow with ``1 + c``), which is what the functions take.

The contact model is an argument (``contact=``, ``impact_contact.py``): ``PaperContact()`` (the
default) is the model above, in which the contact point's velocity jumps along ``n̂`` only;
``CoulombContact(mu)`` bounds every impulse in the friction cone (``mu = 0``: frictionless, exact),
as a central jump and a spread. Measured in MuJoCo (planar wall strike, frictionless soft contact,
222 strikes): the joint-velocity jump lies along ``M^-1 J^T n̂``, the frictionless model's direction, to a
relative 1.9e-7, while the paper's direction misses by 70 % (median) and under-predicts the light distal
joint's jump in 221 of the 222 (median 4x); ``docs/impact.md`` has the measurement.

Constraints (``impact_constraints``), with ``dt`` the control step and the impact assumed at the
end of the step about to be commanded (``v_pre = v + a dt``, the paper's (13)):

    (16) position:          (q_min - q) / dt <= dq <= (q_max - q) / dt
    (17) velocity:          -v_max <= v_pre + dq <= v_max
    (20) impulsive torque:  -tau_imp_max <= dtau <= tau_imp_max

(16) is the paper's with the signs of the printed equation corrected so that ``q + dt dq`` stays in
range; (17) bounds the true post-impact velocity ``v + a dt + dq`` (the paper writes ``v(t_k)`` in
place of ``v_pre`` after "removing q̈ from both sides"; keeping ``a dt`` makes the rows exact).
As in the paper the rows are not gated by the sign of ``w``: they also bound a retreat.

Speed cap (``impact_speed_cap``): the largest approach velocity ``w >= 0`` for which the jumps
predicted at a given pre-impact state satisfy (16), (17), (20). Each row is linear in ``w`` and
holds at ``w = 0`` when the state itself is inside its limits, so the admissible set is ``[0, cap]``
with ``cap = min_i bound_i / ((1 + c) |slope_i|)`` (the bound on the side the jump goes).

Regularisation (near singular configurations ``A`` loses rank and ``M_eq`` blows up): we use
``M_eq = (A + lam I)^-1`` with ``lam = reg * trace(A) / 3 + tiny``. Where ``sigma_min(A) >> lam``
this is ``A^-1`` to relative error ``~ lam / sigma_min``; near a singularity it *underestimates* the
equivalent mass along the lost direction (bounded by ``1 / lam``), so the predicted jumps there are
a lower estimate. The default ``reg = 1e-6`` only matters for ``sigma_min / trace(A) < ~1e-4``.
Denominators of the cap are floored (``safe_math.tiny_floor``): a row whose slope is zero gives a
large finite cap, never inf or NaN; values and gradients are finite for finite input.

Everything broadcasts over leading batch dimensions (``M`` (..., n, n), ``J`` (..., 3, n) or
(..., 6, n) of which the first three rows, the linear part, are used), runs under jit/vmap/grad and
works in float32 and float64. Units: SI (m, s, rad, N, N m).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxlimits._src.impact_contact import PAPER, check_contact, minv_jt, regularised
from jaxlimits._src.qp_checks import concrete
from jaxlimits._src.safe_math import tiny_floor

DEFAULT_REG = 1e-6


class ImpactJump(NamedTuple):
    """The predicted jumps for one contact (shapes for a batch ``...``).

    w: (...,) contact-normal velocity ``n̂ . J v`` before the impact [m/s] (> 0: approaching).
    dq: (..., n) joint-velocity jump (22) [rad/s].
    dtau: (..., n) impulsive joint torque (19) [N m].
    force: (..., 3) average impulsive contact force (5) [N].
    dq_dw, dtau_dw: (..., n) the jumps per unit ``w`` (``-(1 + c) u`` and ``-(1 + c) t / dt_imp``).
    dq_spread, dtau_spread: (..., n) >= 0, per unit ``w``: a strike at ``w >= 0`` gives a jump in
      ``theta w (dq_dw ± dq_spread)``, ``theta in [0, 1]`` (componentwise; likewise ``dtau``). Zero for an
      exact contact model (``PaperContact``, ``CoulombContact(0)``), where ``dq`` is the jump.
    """

    w: jnp.ndarray
    dq: jnp.ndarray
    dtau: jnp.ndarray
    force: jnp.ndarray
    dq_dw: jnp.ndarray
    dtau_dw: jnp.ndarray
    dq_spread: jnp.ndarray
    dtau_spread: jnp.ndarray


class SpeedCap(NamedTuple):
    """The largest admissible approach velocity ``cap = min(position, velocity, torque)`` [m/s], (...,)."""

    cap: jnp.ndarray
    position: jnp.ndarray
    velocity: jnp.ndarray
    torque: jnp.ndarray


# ---- eager checks ------------------------------------------------------------------------------
def _check(M, J, normal=None, **scalars):
    """Eager shape/value checks; value checks only for concrete inputs. Raises ``ValueError`` naming the field."""
    M, J = jnp.asarray(M), jnp.asarray(J)
    if M.ndim < 2 or M.shape[-1] != M.shape[-2]:
        raise ValueError(f"impact: M must be (..., n, n), got shape {M.shape}")
    n = M.shape[-1]
    if J.ndim < 2 or J.shape[-2] not in (3, 6) or J.shape[-1] != n:
        raise ValueError(f"impact: J must be (..., 3, {n}) or (..., 6, {n}), got shape {J.shape}")
    for name, arr in (("M", concrete(M)), ("J", concrete(J))):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise ValueError(f"impact: {name} must be finite, got {arr[~np.isfinite(arr)][:5].tolist()}")
    if normal is not None:
        normal = jnp.asarray(normal)
        if normal.shape[-1:] != (3,):
            raise ValueError(f"impact: normal must be (..., 3), got shape {normal.shape}")
        normal_value = concrete(normal)
        if normal_value is not None:
            nn = np.linalg.norm(normal_value, axis=-1)
            if not np.all(np.abs(nn - 1.0) < 1e-3):
                raise ValueError(f"impact: normal must be a unit vector, got norm {nn.tolist()}")
    for name, val in scalars.items():
        arr = None if val is None else concrete(val)
        if arr is None:
            continue
        if name == "c_max":
            ok, what = np.all((arr >= 0) & (arr <= 1)), "in [0, 1]"
        elif name == "reg":
            ok, what = np.all(arr >= 0), ">= 0"
        else:
            ok, what = np.all(arr > 0), "> 0"
        if not (np.all(np.isfinite(arr)) and ok):
            raise ValueError(f"impact: {name} must be finite and {what}, got {arr.tolist()}")


def check_restitution(c_min, c_max) -> float:
    """Validate a restitution range eagerly and return its worst case ``c_max`` (0 <= c_min <= c_max <= 1)."""
    c_min, c_max = float(c_min), float(c_max)
    if not (np.isfinite(c_min) and np.isfinite(c_max) and 0.0 <= c_min <= c_max <= 1.0):
        raise ValueError(f"impact: restitution range must satisfy 0 <= c_min <= c_max <= 1, got [{c_min}, {c_max}]")
    return c_max


# ---- model ------------------------------------------------------------------------------------
def _lin(J):
    return J[..., :3, :]


def equivalent_mass(M, J, reg=DEFAULT_REG):
    """The equivalent (operational-space) mass ``M_eq = (J M^-1 J^T + lam I)^-1`` (6), ``(..., 3, 3)`` [kg].

    ``M``: (..., n, n) joint-space inertia; ``J``: (..., 3 or 6, n) contact-point Jacobian (linear rows
    used). ``reg``: relative regularisation (see the module docstring); ``reg=0`` leaves only a
    ``tiny`` floor, i.e. the exact inverse where ``A`` is invertible.
    """
    _check(M, J, reg=reg)
    M, J = _promote(M, J)
    J = _lin(J)
    Ar = regularised(J @ minv_jt(M, J), reg)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=Ar.dtype), Ar.shape)
    return jnp.linalg.solve(Ar, eye)


def _promote(*xs):
    dtype = jnp.result_type(*[jnp.asarray(x) for x in xs], jnp.float32)
    return [jnp.asarray(x, dtype) for x in xs]


def impact_jump(M, J, normal, v, c_max, dt_impact, reg=DEFAULT_REG, contact=PAPER) -> ImpactJump:
    """The jumps an impact would cause at joint velocity ``v`` (eqs. 3-5, 19, 22; ``contact``'s model).

    Args:
      M: (..., n, n) joint-space inertia [kg m^2]. J: (..., 3 or 6, n) contact Jacobian.
      normal: (..., 3) unit strike direction (into the wall). v: (..., n) pre-impact joint velocity [rad/s].
      c_max: worst-case restitution coefficient (upper end of ``[c_min, c_max]``, see
        ``check_restitution``), a scalar. dt_impact: impact duration [s] (not the control step), a scalar.
      reg: relative regularisation of ``J M^-1 J^T``.
      contact: the contact model (``impact_contact``): ``PaperContact()`` (the paper's (22), default) or
        ``CoulombContact(mu)`` (an impulse in the friction cone; ``mu = 0``: frictionless).
    Returns ``ImpactJump``: the central jumps (for an exact model, the jumps), linear in ``w`` (not gated
    by its sign), and the spreads around them (zero for an exact model).
    """
    _check(M, J, normal, c_max=c_max, dt_impact=dt_impact, reg=reg)
    contact = check_contact(contact)
    M, J, normal, v = _promote(M, J, normal, v)
    dtype = M.dtype
    k = 1.0 + jnp.asarray(c_max, dtype)
    kt = k / jnp.asarray(dt_impact, dtype)
    unit = contact.unit_jumps(M, _lin(J), normal, reg)
    lead = jnp.broadcast_shapes(unit.g.shape, v.shape)
    g, u, t, us, ts, v = (jnp.broadcast_to(x, lead) for x in (unit.g, unit.u, unit.t, unit.u_spread, unit.t_spread, v))
    impulse = jnp.broadcast_to(unit.impulse, lead[:-1] + (3,))
    w = jnp.sum(g * v, axis=-1)
    dq_dw = -k * u
    dtau_dw = -kt * t
    dq = dq_dw * w[..., None]
    dtau = dtau_dw * w[..., None]
    force = -kt * w[..., None] * impulse
    return ImpactJump(w, dq, dtau, force, dq_dw, dtau_dw, k * us, kt * ts)


def _bounds(q, v_pre, q_min, q_max, v_max, tau_imp_max, dt):
    """Per-row ``(lo, hi)`` for the jumps: position (16), velocity (17) on dq; torque (20) on dtau."""
    pos = ((q_min - q) / dt, (q_max - q) / dt)
    vel = (-v_max - v_pre, v_max - v_pre)
    tau = (-tau_imp_max, tau_imp_max)
    return pos, vel, tau


def impact_speed_cap(
    M, J, normal, q, v, limits, tau_imp_max, dt, c_max, dt_impact, reg=DEFAULT_REG, v_pre_range=None, contact=PAPER
) -> SpeedCap:
    """The largest approach velocity ``w >= 0`` whose predicted jumps satisfy (16), (17), (20).

    The jumps are those of ``impact_jump`` at the state ``(q, v)`` (the pre-impact state; for the
    shield ``v`` is the velocity at the impact instant), with the row bounds of (16) and (17)
    evaluated at ``q`` and ``v``. A bound already violated at ``w = 0`` (state outside its limits)
    gives a cap of 0 for that family. Returns ``SpeedCap`` (each (...,), [m/s], finite, >= 0).

    Args: ``limits`` a ``jl.JointLimits`` (``q_min, q_max, v_max`` used); ``tau_imp_max`` (n,) or
    scalar, the impulsive torque bound [N m] (> 0); ``dt`` the control step [s]; the rest as in
    ``impact_jump``. ``v_pre_range``: optional ``(v_lo, v_hi)`` (..., n): the pre-impact velocity is
    only known to lie in this box (e.g. ``v + dt [lower, upper]`` for the next step's commands); (17)
    then holds for every velocity in it: ``-v_max - v_lo <= dq <= v_max - v_hi``. ``contact``: the
    contact model; with a spread (``CoulombContact(mu > 0)``) every jump of its set must satisfy the
    rows: the upper bounds by ``w (dq_dw + dq_spread)``, the lower by ``w (dq_dw - dq_spread)``.
    """
    _check(M, J, normal, c_max=c_max, dt_impact=dt_impact, dt=dt, reg=reg, tau_imp_max=tau_imp_max)
    jump = impact_jump(M, J, normal, v, c_max, dt_impact, reg, contact)
    dtype = jump.dq.dtype
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    q, v = jnp.broadcast_to(f(q), jump.dq.shape), jnp.broadcast_to(f(v), jump.dq.shape)
    b = lambda x: jnp.broadcast_to(f(x), q.shape)  # noqa: E731
    pos, vel, tau = _bounds(q, v, b(limits.q_min), b(limits.q_max), b(limits.v_max), b(tau_imp_max), f(dt))
    if v_pre_range is not None:
        v_lo, v_hi = b(v_pre_range[0]), b(v_pre_range[1])
        vel = (-b(limits.v_max) - v_lo, b(limits.v_max) - v_hi)
    floor = tiny_floor(dtype)

    def cap_of(slope, spread, lo_hi):
        lo, hi = lo_hi
        # for w >= 0 the jump lies in w [slope - spread, slope + spread] (and its multiples by [0, 1]): the
        # upper end meets hi where it is > 0, the lower end meets lo where it is < 0
        up, down = slope + spread, slope - spread
        cap_up = jnp.where(up > 0, jnp.maximum(hi, 0.0) / jnp.maximum(up, floor), 1.0 / floor)
        cap_down = jnp.where(down < 0, jnp.maximum(-lo, 0.0) / jnp.maximum(-down, floor), 1.0 / floor)
        # a row already violated at w = 0 (lo > 0 or hi < 0) caps the family at 0, even where the jump would
        # move back toward the bound: the post-impact state would still be outside it
        room = jnp.where((lo > 0) | (hi < 0), 0.0, jnp.minimum(cap_up, cap_down))
        return jnp.min(room, axis=-1)

    cp = cap_of(jump.dq_dw, jump.dq_spread, pos)
    cv = cap_of(jump.dq_dw, jump.dq_spread, vel)
    ct = cap_of(jump.dtau_dw, jump.dtau_spread, tau)
    cap = jnp.minimum(jnp.minimum(cp, cv), ct)
    return SpeedCap(cap, cp, cv, ct)


def impact_constraints(M, J, normal, q, v, limits, tau_imp_max, dt, c_max, dt_impact, reg=DEFAULT_REG, contact=PAPER):
    """The constraints (16), (17), (20) as ``G a <= h`` in the joint acceleration ``a`` [rad/s^2].

    The impact is predicted at the end of the step: ``v_pre = v + a dt`` (13), so
    ``w(a) = g . v + dt g . a`` with ``g = J^T n̂`` and every jump is affine in ``a``.

    Returns ``(G, h)``: ``G`` (..., 6 n, n), ``h`` (..., 6 n); rows in the order
    [(16) upper, (16) lower, (17) upper, (17) lower, (20) upper, (20) lower], each block ``n`` rows
    (joint order). Ungated by the sign of ``w``, as in the paper. With a contact model that has a
    spread the jump set's two extremes ``w (dq_dw ± dq_spread)`` each get these ``6 n`` rows (``+``
    first): ``G`` (..., 12 n, n).
    """
    _check(M, J, normal, c_max=c_max, dt_impact=dt_impact, dt=dt, reg=reg, tau_imp_max=tau_imp_max)
    jump = impact_jump(M, J, normal, v, c_max, dt_impact, reg, contact)
    dtype = jump.dq.dtype
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    lead = jump.dq.shape
    q, v = jnp.broadcast_to(f(q), lead), jnp.broadcast_to(f(v), lead)
    dt = f(dt)
    g = jnp.broadcast_to(jnp.einsum("...in,...i->...n", _lin(f(J)), f(normal)), lead)  # J^T n̂: w = g . v
    b = lambda x: jnp.broadcast_to(f(x), lead)  # noqa: E731
    (plo, phi), (_, _), (tlo, thi) = _bounds(
        q, v, b(limits.q_min), b(limits.q_max), b(limits.v_max), b(tau_imp_max), dt
    )
    vmax = b(limits.v_max)
    w0 = jump.w[..., None]
    n = q.shape[-1]

    def rows(sq, st):
        # jump(a) = s * (w0 + dt g . a): rows  s dt g^T a  <=  hi - s w0  /  -s dt g^T a <= -lo + s w0
        outer_q = dt * sq[..., :, None] * g[..., None, :]  # (..., n, n)
        outer_t = dt * st[..., :, None] * g[..., None, :]
        eye = jnp.broadcast_to(jnp.eye(n, dtype=dtype), outer_q.shape)
        # (17): v + dt a + s (w0 + dt g.a) <= v_max   and   >= -v_max
        vel_G = dt * eye + outer_q
        G = jnp.concatenate([outer_q, -outer_q, vel_G, -vel_G, outer_t, -outer_t], axis=-2)
        bc = lambda x: jnp.broadcast_to(x, G.shape[:-2] + (n,))  # noqa: E731
        h = jnp.concatenate(
            [
                bc(phi - sq * w0),
                bc(-plo + sq * w0),
                bc(vmax - v - sq * w0),
                bc(vmax + v + sq * w0),
                bc(thi - st * w0),
                bc(-tlo + st * w0),
            ],
            axis=-1,
        )
        return G, h

    if contact.exact:
        return rows(jump.dq_dw, jump.dtau_dw)
    G_up, h_up = rows(jump.dq_dw + jump.dq_spread, jump.dtau_dw + jump.dtau_spread)
    G_dn, h_dn = rows(jump.dq_dw - jump.dq_spread, jump.dtau_dw - jump.dtau_spread)
    return jnp.concatenate([G_up, G_dn], axis=-2), jnp.concatenate([h_up, h_dn], axis=-1)


def speed_cap_halfspace(M, J, normal, v, cap, dt, box=None):
    """The cap as one halfspace in ``a``; returns ``(G (..., 1, n), h (..., 1))``.

    ``box=None``: the contact-normal speed at the end of the step, ``w(a) = g . (v + a dt) <= cap``, with
    ``g = J^T n̂`` (``J`` the linear rows; Wang & Kheddar (17) holds for ``w <= cap``).

    ``box=(lower, upper)`` (``(..., n)`` [rad/s^2], the step's acceleration bounds, finite): the cap also holds after
    any joints brake toward rest, ``w_+(a) = sum_i max(0, x_i(a)) <= cap`` with ``x_i = g_i (v_i + a_i dt)``, the
    largest normal speed the end-of-step velocities can show when any subset of joints slows down (for this
    ``J``). The acceleration bounds only ever force a joint toward rest (braking before a position or
    velocity limit), so a joint whose motion points away from the contact and cancels the others cannot,
    by braking later, push ``w`` over the cap: the one-step row allows that cancellation and then meets a box
    that no longer reaches its halfspace (measured on the planar wall: every strike over the bound under
    random walks followed 8+ such steps). Each ``max(0, x_i)`` is replaced by its chord over ``x_i``'s range
    on the box (``max(0, .)`` is convex, so the chord lies above it): one row that implies ``w_+ <= cap``
    and ``w <= cap``, and meets the box exactly when ``w_+ <= cap`` can be met (both minima over the box are
    ``sum_i max(0, min_box x_i)``).
    """
    M, J, normal, v, cap = _promote(M, J, normal, v, cap)
    g = jnp.einsum("...in,...i->...n", _lin(J), jnp.broadcast_to(normal, J.shape[:-2] + (3,)))
    dt = jnp.asarray(dt, g.dtype)
    if box is None:
        return (dt * g)[..., None, :], (cap - jnp.sum(g * v, axis=-1))[..., None]
    lower, upper = (jnp.asarray(b, g.dtype) for b in box)
    x_l, x_u = g * (v + lower * dt), g * (v + upper * dt)
    x_lo, x_hi = jnp.minimum(x_l, x_u), jnp.maximum(x_l, x_u)
    p_lo, p_hi = jnp.maximum(x_lo, 0.0), jnp.maximum(x_hi, 0.0)
    width = x_hi - x_lo
    wide = width > 0
    # the chord's slope over [x_lo, x_hi]; a point range (g_i = 0 or lower_i = upper_i) keeps the constant
    slope = jnp.where(wide, (p_hi - p_lo) / jnp.where(wide, width, 1.0), 0.0)
    # sum_i p_lo_i + slope_i (x_i(a) - x_lo_i) <= cap, with x_i(a) = g_i v_i + g_i dt a_i
    G = slope * g * dt
    h = cap - jnp.sum(p_lo + slope * (g * v - x_lo), axis=-1)
    return G[..., None, :], h[..., None]
