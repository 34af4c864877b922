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
are measured against the model's own limits. Where a substep deviates more (contacts within the
substep, joint damping fast against it: Gymnasium's Ant), the Gymnasium wrapper retakes it
(``RK4_RESTEP``, ``actuation.CActuation``).

MJX computes in float32, where a stiff position servo on a light link realises its acceleration only to
the rounding of its ``ctrl`` (``Robot.ctrl_quantum``: Kinova Gen3's wrists, kp 500 and no armature, miss it
by up to 4e-3 rad/s^2, and riding ``v_max`` overshot it by 5e-5 rad/s in most steps). With
``realisation_margin`` (the Brax wrapper's) the velocity limits are tightened by ``QUANTUM_SAFETY`` times the
velocity that error gives over a control step, ``n_frames h ctrl_quantum``, the positions by that times
``dt``; for motors it is below 1e-6 of ``v_max`` (Brax reacher, pusher, ant: 2-6e-7).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import jaxlimits as jl
from jaxlimits.envs.impact_point import remove_excess
from jaxlimits.envs.robot import Robot

METHODS = ("viability", "jerk", "naive", "none")
RK4_MARGIN = 1e-3
# C MuJoCo's RK4 substeps are retaken where their realised acceleration leaves the band by more than this
# fraction of the margin's worth per substep, RK4_RESTEP RK4_MARGIN v_max / dt (actuation.CActuation); smaller
# deviations use at most a quarter of the velocity margin over the step, an eighth of the position margin
RK4_RESTEP = 0.25
# the first (torque-aware) solve in the acceleration: the same problem as in the torque, cheaper to settle
# (``_torque_space``); False keeps the torque-space form (the A/B of docs/shield.md and tests/test_joint_shield.py)
ACCEL_SPACE_FIRST = True
BOUNDS_TOL = 1e-3  # [a_max] torque-space answers this close to the bounds are the bounds (solver roundoff)
QUANTUM_SAFETY = 2.0  # the realisation margin's factor over the float32 ctrl rounding's velocity error


def _reduce(op, terms: dict, full):
    """``op`` over the terms other than ``"acceleration"``, widened to contain ``full`` (the bounds)."""
    out = None
    for name, t in terms.items():
        if name != "acceleration":
            out = t if out is None else op(out, t)
    wide = jnp.minimum if op is jnp.maximum else jnp.maximum
    return full if out is None else wide(out.astype(full.dtype), full)


class Decision(NamedTuple):
    """One control step's decision, ``(..., n)`` each (``nonfinite`` ``(...)``)."""

    a_safe: jax.Array  # [rad/s^2] the acceleration to realise
    lower: jax.Array
    upper: jax.Array
    viable: jax.Array  # bool, the state was in the viability kernel
    nonfinite: jax.Array  # bool, a_des had a NaN/inf entry and braking was substituted
    conflict: jax.Array  # bool, not even the position/velocity/viability terms were realisable (torque box held)
    # the impact cap (``impact_point``), ``(...)`` each; 0 without one
    impact_cap: jax.Array  # [m/s] the largest safe approach speed of the impact point
    impact_excess: jax.Array  # [m/s] how far a_safe's end-of-step approach speed exceeds it (no command met it)
    impact_active: jax.Array  # bool, the cap applied (the point near its surface, or no surface given)


class SafeAcceleration:
    """Bounds and projection for ``robot`` over ``n_frames`` substeps; see the module docstring."""

    def __init__(
        self,
        robot: Robot,
        n_frames: int,
        method: str = "viability",
        gradient: str = "exact",
        realisation_margin: bool = False,
        impact=None,
    ):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if int(n_frames) != n_frames or n_frames < 1:
            raise ValueError(f"n_frames must be a positive integer, got {n_frames!r}")
        if gradient not in jl.PROJECTION_GRADIENTS:
            raise ValueError(f"gradient must be one of {jl.PROJECTION_GRADIENTS}, got {gradient!r}")
        if method == "jerk" and robot.limits.j_max is None:
            raise ValueError("method='jerk' needs j_max (argument or <numeric name='jaxlimits_j_max'>)")
        if impact is not None and method == "none" and impact.enforce:
            raise ValueError(
                "an enforced impact cap needs the bounds of a method: 'viability', 'jerk' or 'naive', not 'none' "
                "(unshielded, ImpactPoint(enforce=False) measures the strikes only)"
            )
        self.robot, self.method, self.gradient = robot, method, gradient
        self.impact = impact  # an ``impact_point.ImpactModel`` or None
        self.n_frames = int(n_frames)
        self.dt = robot.timestep * self.n_frames
        self.integrator = robot.integrator
        self.substeps = self.n_frames if self.integrator == "semi_implicit" else 1
        lim = robot.limits
        if self.integrator == "zoh":
            m_q = RK4_MARGIN * lim.v_max * self.dt
            lim = lim.replace(q_min=lim.q_min + m_q, q_max=lim.q_max - m_q, v_max=lim.v_max * (1.0 - RK4_MARGIN))
        if realisation_margin:
            m_v = QUANTUM_SAFETY * self.n_frames * robot.timestep * np.asarray(robot.ctrl_quantum)
            too_big = np.flatnonzero(m_v >= 0.01 * np.asarray(lim.v_max))
            if too_big.size:
                bad = {robot.names[i]: float(m_v[i]) for i in too_big}
                raise ValueError(
                    f"joints {bad} [rad/s]: float32 ctrl rounding alone moves the velocity by over 1 % of v_max per "
                    "control step (a stiff servo on a nearly massless link); add armature or lower the servo's kp"
                )
            lim = lim.replace(q_min=lim.q_min + m_v * self.dt, q_max=lim.q_max - m_v * self.dt, v_max=lim.v_max - m_v)
        self.limits = lim
        if method in ("viability", "jerk", "naive"):
            jl.make_discretisation(self.dt, self.integrator, self.substeps)  # validates eagerly
        if method in ("viability", "jerk"):
            jl.check_condition_11(lim, self.dt)
        if method == "jerk":  # else raised at the first trace of a step (the bounds' own check)
            placed = robot.bound_positions(np.zeros(robot.n), self.dt, lim)[1]
            jl.check_jerk_condition(placed, self.dt, self.integrator, self.substeps)

    def __call__(self, q, v, a_des, a_prev=None, torque=None, impact_terms=None) -> Decision:
        """``impact_terms``: ``(M, J, J_rate, point)`` (``(n, n)``, ``(3, n)``, ``(3, n)``, ``(3,)``) at the state, for the impact cap the shield was
        built with (``impact_point``; required then): its row ``G a <= h`` joins the projection (the box QP
        ``jl.solve_box_qp``; with ``torque``, the first solve's rows; where the bounds and the torques leave no
        command meeting it, they hold and the excess is ``Decision.impact_excess``).

        ``torque``: optional ``actuation.TorqueModel`` (``tau = M a - f`` in ``[tau_lo, tau_hi]``). Then the
        decision is made in torque space, where the realisable set is a box (``_torque_space``):
        ``jl.solve_box_qp`` projects ``tau_des = M a_des - f`` onto the torque box and the bounds as
        halfspaces ``M^-1 (tau + f) <= upper`` (and ``>= lower``), in the metric ``M^-1`` (Gauss's: the
        kinetic-energy distance ``(a - a_des)^T M (a - a_des)`` of the accelerations; better conditioned
        than the Euclidean one's ``M^-2``), so ``a_safe`` is the nearest realisable acceleration inside the
        bounds. Where none is, the acceleration limit gives way before the position, velocity and
        viability terms (measured by ``beyond_bounds``); where not even those are realisable
        (``Decision.conflict``), physics decides what happens whatever is commanded: the torque box holds
        and the terms are met with the least violation."""
        dtype = jnp.result_type(v)
        a_max = jnp.asarray(self.limits.a_max, dtype)
        bad = ~jnp.all(jnp.isfinite(a_des), axis=-1, keepdims=True)
        a_in = jnp.where(bad, -jnp.sign(v) * a_max, a_des)
        if self.method == "none":
            inf = jnp.full(jnp.shape(v), jnp.inf, dtype)
            zero = jnp.zeros(jnp.shape(v)[:-1], dtype)
            ok = jnp.ones(jnp.shape(v), bool)
            no = jnp.zeros_like(bad[..., 0])
            return Decision(a_in, -inf, inf, ok, bad[..., 0], no, zero, zero, no)
        q_eff, lim = self.robot.bound_positions(q, self.dt, self.limits)
        kwargs = dict(method=self.method, integrator=self.integrator, substeps=self.substeps)
        if self.method == "jerk":
            kwargs["a_prev"] = jnp.zeros_like(v) if a_prev is None else a_prev
        b = jl.acc_bounds(q_eff, v, lim, self.dt, **kwargs)
        rows = None
        cap = jnp.zeros(jnp.shape(v)[:-1], dtype)
        active = jnp.zeros(jnp.shape(v)[:-1], bool)
        if self.impact is not None:
            if impact_terms is None:
                raise ValueError("this shield has an impact cap: pass impact_terms=(M, J, J_rate, point)")
            G, h, cap, u, active = self.impact.halfspace(*impact_terms, q_eff, v, lim, self.dt, b.lower, b.upper)
            rows = (G, h)
        measured = rows
        if rows is not None and not self.impact.enforce:
            rows = None  # measured only: the excess below is what the decision without the cap gives
        if rows is not None:  # the command's excess removed along u first
            a_in = remove_excess(a_in, G[..., 0, :], h, u)
        if torque is None and rows is None:
            a_safe = jl.project_box(a_in, b.lower, b.upper, gradient=self.gradient)
            conflict = jnp.zeros(jnp.shape(v)[:-1], bool)
        elif torque is None:
            a_safe = jl.solve_box_qp(a_in, b.lower, b.upper, G=rows[0], h=rows[1], gradient=self.gradient).x
            conflict = jnp.zeros(jnp.shape(v)[:-1], bool)
        else:
            # the safety terms: the viability family's (for "jerk" too: its kernel contains the jerk kernel,
            # so giving way on the jerk box keeps the position and velocity limits)
            hard = dict(kwargs, method="viability" if self.method == "jerk" else self.method)
            hard.pop("a_prev", None)
            terms = jl.bound_terms(q_eff, v, lim, self.dt, **hard)
            a_safe, conflict = self._torque_space(a_in, b, terms, torque, rows)
        excess = jnp.zeros_like(cap)
        if measured is not None:
            G, h = measured
            excess = jnp.maximum(jnp.einsum("...n,...n->...", G[..., 0, :], a_safe) - h[..., 0], 0.0)
        return Decision(a_safe, b.lower, b.upper, b.viable, bad[..., 0], conflict, cap, excess, active)

    def _torque_space(self, a_in, b, terms, torque, impact_rows=None):
        """The torque-space decision (see ``__call__``) and its conflict rule; returns ``(a_safe, conflict)``.
        ``impact_rows``: ``(G (1, n), h (1,))`` the impact cap's row in the acceleration, added to step 1's rows
        (where it makes step 1 infeasible, step 1 runs again without it, from the same command ``a_in``, whose
        excess over the row was removed along ``u``: the cap is the first to give way, and the answer is the
        realisable acceleration nearest to the one meeting it, braking the point as hard as the bounds and the
        torques allow. From the command before that correction, as before, a point approaching too fast for the
        cap to be met in one step was not braked at all: measured on a block dropped on a floor,
        ``tests/test_strike_record.py``).

        1. ``tau_des = M a_des - f`` projected onto the torque box and the bounds as halfspaces
           ``lower <= M^-1 (tau + f) <= upper``: the nearest realisable acceleration inside the bounds
           (clipped into them).
        2. Where no realisable acceleration lies inside the bounds, the acceleration limit (``a_max``, the
           jerk box) gives way, and only it: ``M a_c - f`` projected onto the box and the bounds' *safety* terms
           (position, velocity, viability; ``hard_lo``, ``hard_up``). The typical case is physics braking
           harder than ``a_max`` (a servo near its limit cannot hold back gravity, its target cannot pass
           the limit), which no command prevents and which is safe; clipping step 1's least-violation
           answer into the bounds instead saturates the actuators, whose coupling then moves the other
           joints (measured on the servo Panda). ``SafeAcceleration.beyond_bounds`` measures it.
        3. Where not even the safety terms are realisable (``conflict``): step 2's least violation, clipped
           into them (best effort). A non-finite solve falls back to ``a_c`` (counted as a conflict).

        A solve that did not converge counts as failed, as an infeasible one does (its iterate may lie far
        outside the torque rows: measured once on the UR5e, 72 N m past the elbow's limit, then a ``v_max``
        overshoot of 0.017 rad/s; ``tests/test_joint_shield.py``).

        Under ``vmap`` both solves run (a batch's active-set loop runs until its slowest member is done); for a
        single problem step 2 runs only where step 1 failed. Step 2 starts at ``a_c``, realisable in most
        states, where it stops after its first iteration. (Stacking both steps into one batched solve compiles
        one QP program instead of two, 15 s less per shielded Brax step, but made Brax ``pusher``'s step at
        batch 256 cost +115 % over the unwrapped env instead of +47 %, measured: not done.)"""
        M, f = torque.M_ss, torque.f_s

        def solve_in_acceleration(a_from, accel_rows=None):
            # the same problem, written in the acceleration (a = M^-1 (tau + f)): the bounds are the box, the
            # torque limits the rows ``tau_lo <= M a - f <= tau_hi``; the objective (a - a_from)^T M (a - a_from)
            # is Gauss's metric of before, so where the problem is feasible the answer is the same point
            rows = jnp.concatenate([M, -M], axis=-2)
            h = jnp.concatenate([torque.tau_hi + f, -(torque.tau_lo + f)], axis=-1)
            if accel_rows is not None:
                rows = jnp.concatenate([rows, accel_rows[0].astype(rows.dtype)], axis=-2)
                h = jnp.concatenate([h, accel_rows[1].astype(h.dtype)], axis=-1)
            res = jl.solve_box_qp(a_from, b.lower, b.upper, M, G=rows, h=h, gradient=self.gradient)
            ok = jnp.all(jnp.isfinite(res.x), axis=-1) & res.converged
            return res.x, res.infeasible | ~ok

        def solve(a_from, lo, hi, accel_rows=None):
            # in the torque (inside the give-way branch: for one problem, computed only where it runs)
            Minv = jnp.linalg.inv(M)
            Minv = 0.5 * (Minv + jnp.swapaxes(Minv, -1, -2))
            a0 = (Minv @ f[..., None])[..., 0]
            G = jnp.concatenate([Minv, -Minv], axis=-2)
            tau = (M @ a_from[..., None])[..., 0] - f
            h = jnp.concatenate([hi - a0, a0 - lo], axis=-1)
            if accel_rows is not None:  # G_a a <= h_a with a = a0 + M^-1 tau
                G_a, h_a = (x.astype(G.dtype) for x in accel_rows)
                G = jnp.concatenate([G, G_a @ Minv], axis=-2)
                h = jnp.concatenate([h, h_a - (G_a @ a0[..., None])[..., 0]], axis=-1)
            res = jl.solve_box_qp(tau, torque.tau_lo, torque.tau_hi, Minv, G=G, h=h, gradient=self.gradient)
            a = a0 + (Minv @ res.x[..., None])[..., 0]
            # never a NaN to the simulator: a failed solve (ill-conditioned M in float32) is not used
            ok = jnp.all(jnp.isfinite(a), axis=-1) & res.converged
            return a, res.infeasible | ~ok

        a_c = jnp.clip(a_in, b.lower, b.upper)

        # from the command itself, not its clip: from the clip, the nearest realisable point in this metric
        # let a light joint drift against its command (measured: Pusher-v5's shoulder pan ran to its lower
        # limit under an all-upper action, tests/test_gym_shield.py), although that start made the batch's
        # solves ~4x cheaper (Brax pusher, batch 256)
        def first(a_from, rows=None):
            if ACCEL_SPACE_FIRST:
                return solve_in_acceleration(a_from, rows)
            return solve(a_from, b.lower, b.upper, rows)

        a_full, fail_full = first(a_in, impact_rows)
        if impact_rows is not None:  # the cap gives way first: step 1 again without its row where it failed
            if jnp.ndim(fail_full) == 0:
                a_full, fail_full = jax.lax.cond(fail_full, lambda: first(a_in), lambda: (a_full, fail_full))
            else:
                a_nocap, fail_nocap = first(a_in)
                a_full = jnp.where(fail_full[..., None], a_nocap, a_full)
                fail_full = fail_full & fail_nocap
        hard_up = _reduce(jnp.minimum, terms["upper"], b.upper)
        hard_lo = _reduce(jnp.maximum, terms["lower"], b.lower)

        def give_way():
            a_hard, fail_hard = solve(a_c, hard_lo, hard_up)
            return jnp.where(jnp.all(jnp.isfinite(a_hard), axis=-1, keepdims=True), a_hard, a_c), fail_hard

        # step 2 is used only where step 1 failed: for one problem (the Gymnasium wrapper's case) a real
        # branch skips its solve, the same answer at half the cost; under vmap both sides run
        if jnp.ndim(fail_full) == 0:
            a_hard, fail_hard = jax.lax.cond(fail_full, give_way, lambda: (a_c, jnp.zeros((), bool)))
        else:
            a_hard, fail_hard = give_way()
        # the solver's roundoff at the bounds is no giving way: within BOUNDS_TOL a_max, snapped into them
        tol = BOUNDS_TOL * jnp.asarray(self.limits.a_max, a_hard.dtype)
        near = (a_hard >= b.lower - tol) & (a_hard <= b.upper + tol)
        a_hard = jnp.where(near, jnp.clip(a_hard, b.lower, b.upper), jnp.clip(a_hard, hard_lo, hard_up))
        use_full = ~fail_full[..., None]
        a_safe = jnp.where(use_full, jnp.clip(jnp.where(use_full, a_full, a_c), b.lower, b.upper), a_hard)
        return a_safe, fail_full & fail_hard

    @staticmethod
    def impact_unmet(dec: Decision):
        """``(...)`` bool: ``dec.a_safe`` leaves the impact cap's row beyond its float32 roundoff (1e-4 of the cap,
        1e-5 m/s): no command inside the bounds and the torques met the cap (``impact_infeasible``)."""
        return dec.impact_excess > 1e-4 * dec.impact_cap + 1e-5

    @staticmethod
    def beyond_bounds(dec: Decision):
        """``(...)`` how far ``dec.a_safe`` lies outside ``[dec.lower, dec.upper]`` [rad/s^2]: 0 without torque
        limits; with them, where the actuators could realise no acceleration inside the bounds (the
        acceleration or jerk limit given way; see ``_torque_space``)."""
        out = jnp.maximum(dec.a_safe - dec.upper, dec.lower - dec.a_safe)
        return jnp.maximum(jnp.max(out, axis=-1), jnp.zeros((), out.dtype))

    def jerk_excess(self, a, a_prev, xp=jnp):
        """How far the held acceleration's change over the step, ``a - a_prev`` ``(n,)`` [rad/s^2], exceeds the
        robot's ``j_max dt`` (its largest over the joints, 0 within; float32, as the decision computes it; the robot
        must have ``j_max``). ``xp``: ``jnp`` (the Brax shield) or ``numpy`` (the Gymnasium wrapper)."""
        f32 = xp.float32
        step_max = xp.asarray(self.robot.limits.j_max, f32) * f32(self.dt)
        return xp.maximum(xp.max(xp.abs(xp.asarray(a, f32) - a_prev) - step_max), f32(0.0))

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
