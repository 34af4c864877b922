"""The shield's decision, shared by the Brax and the Gymnasium wrappers: a safe joint acceleration.

``SafeAcceleration(robot, n_frames, method)`` is a jittable function of
``(q, v, a_des, a_prev) -> Decision``: the bounds of ``jl.acc_bounds`` for the robot's shielded
joints over one control step of ``n_frames`` physics substeps (the discretisation the model's
integrator realises: ``"semi_implicit"`` with ``n_frames`` substeps for Euler/implicitfast, ``"zoh"``
for RK4), and ``a_des`` projected into them (``jl.project_box``). A command with a NaN/inf entry is
replaced, whole, by braking (``-sign(v) a_max``, projected) and flagged (``Decision.nonfinite``).

Methods: ``"viability"`` (Del Prete's exact bounds), ``"jerk"`` (exact with ``|a - a_prev| <= j_max
dt``; needs ``j_max``), ``"naive"`` (eq. 2, the baseline that violates), ``"none"`` (no bounds: the
command as asked, only the NaN guard).

RK4 realises the held acceleration only to second order (``robot.py``): the limits the bounds use
are tightened by ``RK4_MARGIN`` (positions by ``RK4_MARGIN v_max dt``, velocities by
``RK4_MARGIN v_max``), a hundred times the error measured on Gymnasium's Reacher; the violations
are measured against the model's own limits.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

import jaxlimits as jl
from jaxlimits.envs.robot import Robot

METHODS = ("viability", "jerk", "naive", "none")
RK4_MARGIN = 1e-3


class Decision(NamedTuple):
    """One control step's decision, ``(..., n)`` each (``nonfinite`` ``(...)``)."""

    a_safe: jax.Array  # [rad/s^2] the acceleration to realise
    lower: jax.Array
    upper: jax.Array
    viable: jax.Array  # bool, the state was in the viability kernel
    nonfinite: jax.Array  # bool, a_des had a NaN/inf entry and braking was substituted
    conflict: jax.Array  # bool, no acceleration inside the bounds was realisable (torque rows violated)


class SafeAcceleration:
    """Bounds and projection for ``robot`` over ``n_frames`` substeps; see the module docstring."""

    def __init__(self, robot: Robot, n_frames: int, method: str = "viability", gradient: str = "exact"):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if int(n_frames) != n_frames or n_frames < 1:
            raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
        if gradient not in jl.PROJECTION_GRADIENTS:
            raise ValueError(f"gradient must be one of {jl.PROJECTION_GRADIENTS}, got {gradient!r}")
        if method == "jerk" and robot.limits.j_max is None:
            raise ValueError("method='jerk' needs j_max (argument or <numeric name='jaxlimits_j_max'>)")
        self.robot, self.method, self.gradient = robot, method, gradient
        self.n_frames = int(n_frames)
        self.dt = robot.timestep * self.n_frames
        self.integrator = robot.integrator
        self.substeps = self.n_frames if self.integrator == "semi_implicit" else 1
        lim = robot.limits
        if self.integrator == "zoh":
            m_q = RK4_MARGIN * lim.v_max * self.dt
            lim = lim.replace(q_min=lim.q_min + m_q, q_max=lim.q_max - m_q, v_max=lim.v_max * (1.0 - RK4_MARGIN))
        self.limits = lim
        if method in ("viability", "jerk", "naive"):
            jl.make_discretisation(self.dt, self.integrator, self.substeps)  # validates eagerly
        if method in ("viability", "jerk"):
            jl.check_condition_11(lim, self.dt)

    def __call__(self, q, v, a_des, a_prev=None, torque=None) -> Decision:
        """``torque``: optional ``actuation.TorqueModel`` (``tau = M a - f`` in ``[tau_lo, tau_hi]``). Then the
        decision is made in torque space, where the realisable set is a box: ``jl.solve_box_qp`` projects
        ``tau_des = M a_des - f`` onto ``{tau_lo <= tau <= tau_hi, lower <= M^-1 (tau + f) <= upper}`` in the
        metric ``M^-1`` (Gauss's: the kinetic-energy distance ``(a - a_des)^T M (a - a_des)`` of the
        accelerations; better conditioned than the Euclidean one's ``M^-2``), so ``a_safe`` is the nearest
        realisable acceleration inside the bounds. Where none is (``Decision.conflict``), physics decides
        what happens whatever is commanded: the torque box holds and the bounds are met with the least
        violation. ``a_safe`` is then clipped into the bounds (exact bounds; the torque margin absorbs the
        solver's tolerance); a non-finite solve falls back to the clip of the command (counted as a conflict)."""
        dtype = jnp.result_type(v)
        a_max = jnp.asarray(self.limits.a_max, dtype)
        bad = ~jnp.all(jnp.isfinite(a_des), axis=-1, keepdims=True)
        a_in = jnp.where(bad, -jnp.sign(v) * a_max, a_des)
        if self.method == "none":
            inf = jnp.full(jnp.shape(v), jnp.inf, dtype)
            return Decision(a_in, -inf, inf, jnp.ones(jnp.shape(v), bool), bad[..., 0], jnp.zeros_like(bad[..., 0]))
        q_eff, lim = self.robot.bound_positions(q, self.dt, self.limits)
        kwargs = dict(method=self.method, integrator=self.integrator, substeps=self.substeps)
        if self.method == "jerk":
            kwargs["a_prev"] = jnp.zeros_like(v) if a_prev is None else a_prev
        b = jl.acc_bounds(q_eff, v, lim, self.dt, **kwargs)
        if torque is None:
            a_safe = jl.project_box(a_in, b.lower, b.upper, gradient=self.gradient)
            conflict = jnp.zeros(jnp.shape(v)[:-1], bool)
        else:
            M, f = torque.M_ss, torque.f_s
            Minv = jnp.linalg.inv(M)
            Minv = 0.5 * (Minv + jnp.swapaxes(Minv, -1, -2))
            a0 = (Minv @ f[..., None])[..., 0]
            G = jnp.concatenate([Minv, -Minv], axis=-2)
            h = jnp.concatenate([b.upper - a0, a0 - b.lower], axis=-1)
            tau_des = (M @ a_in[..., None])[..., 0] - f
            res = jl.solve_box_qp(tau_des, torque.tau_lo, torque.tau_hi, Minv, G=G, h=h, gradient=self.gradient)
            a_qp = a0 + (Minv @ res.x[..., None])[..., 0]
            # never a NaN to the simulator: a failed solve (ill-conditioned M in float32) falls back to the clip
            ok = jnp.all(jnp.isfinite(a_qp), axis=-1, keepdims=True)
            a_safe = jnp.clip(jnp.where(ok, a_qp, a_in), b.lower, b.upper)
            conflict = res.infeasible | ~ok[..., 0]
        return Decision(a_safe, b.lower, b.upper, b.viable, bad[..., 0], conflict)

    def violations(self, q, v) -> dict:
        """Excess over the model's own limits at one substep's state ``(..., n)``: ``position``, ``velocity``
        (``(...)``, 0 when inside; unlimited joints have no position excess)."""
        lim = self.robot.limits
        dtype = jnp.result_type(q)
        lo, hi = jnp.asarray(lim.q_min, dtype), jnp.asarray(lim.q_max, dtype)
        pos = jnp.where(jnp.asarray(self.robot.limited), jnp.maximum(q - hi, lo - q), 0.0)
        vel = jnp.abs(v) - jnp.asarray(lim.v_max, dtype)
        zero = jnp.zeros((), dtype)
        return {
            "position": jnp.maximum(jnp.max(pos, axis=-1), zero),
            "velocity": jnp.maximum(jnp.max(vel, axis=-1), zero),
        }
