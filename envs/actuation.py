"""Realise a joint acceleration through a model's own actuators, one physics substep at a time.

At a substep's state the integrator solves ``M_eff qacc = qfrc_smooth + qfrc_constraint`` with
``M_eff = M + h D`` (``Robot.implicit_damping``; ``D = 0`` for RK4) and advances
``v+ = v + h qacc``, ``q+ = q + h v+``. Without constraint forces, the shielded dofs get exactly
the acceleration ``a`` when their actuators apply

    tau = [M_eff a_full - f_other]_s,    a_full = (a on the shielded dofs s, a_u on the others u),
    a_u = M_eff,uu^-1 (f_other,u - M_eff,us a)      (only when the chains couple them),

where ``f_other`` is ``qfrc_smooth`` without the shielded actuators' own forces (bias, gravity,
passive forces, the other actuators, applied forces); for RK4 less ``K h v / 2``
(``Robot.rk4_stiffness``: the springs' and servos' average change over the stages). The actuator
force ``gear (gain ctrl + bias)`` is affine in ``ctrl``, so ``ctrl = (tau / gear - bias) / gain``,
then clamped to ``ctrlrange``, and MuJoCo clamps the force to ``forcerange``: a clamp is a
*saturation*, counted with the torque the actuator lacked (``torque_excess`` [N m]).

Constraint forces (contacts, joint limits, equalities) depend on the acceleration, so the formula
above leaves them out. Where a substep has contacts and a ``band`` (the decision's bounds) is given
(joint-limit rows are not the case: the shield keeps the joints inside their limits), the substep's
constraint problem is solved once with that ctrl (``_constraint_stage``); the
shielded dofs' realised acceleration ``r = M_eff^-1 (qfrc_smooth + qfrc_constraint)`` is kept where it
lies inside the band (a push from an object is physics, not an error), and where a contact pushes it
out of the band the actuators get the torque change that brings it back to the band's edge under the
constraints' own response: one Newton step on the solver's piecewise-quadratic problem,

    dr = G dtau,   G = M_eff^-1 M H^-1,   H = M + J^T diag(D active) J      (restricted to the shielded dofs),

exact while the active constraint rows do not change (the solver's Hessian, as MJX's Newton solver
forms it). The torque change is the least one, inside the torque the actuators have left at the substep
(``robot.torque_range`` less what they applied), that puts every shielded dof inside the band (a box QP:
``contact_correction(torque_box=)``); where none does, the band is missed least and the joints are counted
saturated. The unboxed ``dtau = -G^-1 out`` (kept for C MuJoCo's RK4 retakes) is exact where ``G`` is well
conditioned, but against a stiff contact (a ball pressed on a frictionless wall) ``G`` is nearly singular, its torque
pulls the body off the contact the response assumed active, and the joints take it (the wall task on MJX: 26
velocity- and 180 position-violating steps of 3 200, 0 and 4 boxed, those 4 after counted saturations). Then the
substep is solved again with the corrected ctrl and integrated (where the
shielded joints share a tree with unshielded dofs, a floating or planar base or a gripper's fingers: twice,
``MJX_CORRECTION_PASSES``, the second pass from the rows the first one's torque made or broke, on MJX and
in C MuJoCo's Euler/implicitfast; elsewhere once). Brax's ``ant`` and ``humanoid`` run MJX's solver for one
iteration, whose answer does not respond to torque as the converged one: the shielded substeps run at
least ``MJX_MIN_SOLVER_ITERATIONS`` (Brax ``ant``, 3 200 adversarial env-steps: 1 012 position-violating
steps with one pass at the env's one iteration, 318 with two passes, 54 at four iterations and one pass, 0
at four and two). Keeping every
substep's acceleration inside the band keeps the step's limits: the position, velocity and viability
constraints are monotone in each substep's acceleration (positive coefficients in
``q+ = q + h v + h^2 a`` per substep), so the band computed for a held acceleration bounds any
sequence inside it. What the actuators cannot deliver is a saturation (counted). RK4 holds ``ctrl`` over
four stages, each with its own constraint forces: in C MuJoCo a substep that left the band is retaken
(``CActuation._rk4_step_in_band``); MJX's RK4 substeps are not.

Two implementations of the same formula: ``MjxActuation`` (JAX, MJX data; for Brax) and
``CActuation`` (NumPy over C MuJoCo's ``MjData``; for Gymnasium).
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxlimits.envs import mjx_stages

import jaxlimits as jl
from jaxlimits.envs.robot import (
    Robot,
    _implicit_damping,
    _rk4_stiffness,
    actuator_arrays,
    clamp,
    joint_dynamics,
    shrink,
    sub_block,
    torque_range,
)


class Inversion(NamedTuple):
    """The actuator commands for one substep, ``(n,)`` each (``nu`` for ``ctrl_full``)."""

    ctrl: jax.Array  # the shielded actuators' ctrl, clamped to ctrlrange
    torque_excess: jax.Array  # [N m] |needed - deliverable| joint torque, 0 when not saturated
    saturated: jax.Array  # bool


class TorqueModel(NamedTuple):
    """What the decision needs to keep its command realisable: ``tau = M_ss a - f_s`` must lie in
    ``[tau_lo, tau_hi]`` (``(n, n)``, ``(n,)`` each; the ranges already shrunk to ``TORQUE_MARGIN``).
    ``M_ss``, ``f_s``: the shielded joints' block with the unshielded dofs held (``robot.joint_dynamics``
    without ``coupled``): exact for chains the unshielded dofs do not couple. On a floating base the actuation
    realises with those dofs free (the Schur complement), yet rows written that way were measured worse on
    legs that spend their time on the floor, where the held base is the nearer model: Brax ``hopper``, 25 600
    adversarial env-steps, 65 / 30 position / velocity-violating steps instead of 26 / 17 (``ant`` 0 / 0 both;
    Gymnasium ``Ant-v5``'s 600-step test 1 velocity-violating step instead of 0)."""

    M_ss: jax.Array
    f_s: jax.Array
    tau_lo: jax.Array
    tau_hi: jax.Array


def as_slice(idx):
    """``idx`` ``(k,)`` as a ``slice`` when it is a contiguous ascending range (NumPy then indexes with views
    instead of fancy-index copies: the per-substep Python cost of ``CActuation``), else an index array."""
    idx = np.asarray(idx, np.intp)
    if len(idx) and np.all(np.diff(idx) == 1):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


def shielded_torque(xp, robot_arrays, actuator_force):
    """``(n,)`` [N m or N] the shielded actuators' part of ``qfrc_actuator`` on their joints, from their
    ``actuator_force`` ``(n,)``: ``gear force``, with the force held in ``force_range``, where a joint's
    ``actuatorfrcrange`` clamps it (MuJoCo clamps ``qfrc_actuator``, not ``actuator_force``; elsewhere the
    force already lies in the range)."""
    _, _, gear, _, _, _, f_rng = robot_arrays
    return gear * clamp(xp, actuator_force, f_rng[:, 0], f_rng[:, 1])


def _invert(xp, robot_arrays, M_eff, f_other, a, q, v, coupled: bool, dtau=None, tau=None):
    """Shared formula (``xp`` = ``jnp`` or ``numpy``); see the module docstring. ``dtau`` ``(n,)`` [N m]: a
    torque added to the one realising ``a`` (the contact correction; where the actuators lack it, that is a
    saturation, counted with the torque they lacked). ``tau`` ``(n,)`` [N m]: the joint torque to apply,
    given (the boxed contact correction), in place of the one realising ``a`` (``M_eff``, ``f_other``, ``a`` then
    unread)."""
    dofs, other, gear, gain, bias, c_rng, f_rng = robot_arrays
    if tau is None:
        M_s, f_s = joint_dynamics(xp, M_eff, f_other, dofs, other, coupled)
        tau = M_s @ a - f_s
    if dtau is not None:
        tau = tau + dtau
    b = bias[:, 0] + bias[:, 1] * gear * q + bias[:, 2] * gear * v
    force_needed = tau / gear
    ctrl_needed = (force_needed - b) / gain
    ctrl = clamp(xp, ctrl_needed, c_rng[:, 0], c_rng[:, 1])
    force_free = gain * ctrl + b
    force = clamp(xp, force_free, f_rng[:, 0], f_rng[:, 1])
    # saturated = a clamp is active (exact comparisons: the roundoff of gain * ctrl is not a saturation)
    saturated = (ctrl != ctrl_needed) | (force != force_free)
    excess = xp.where(saturated, xp.abs(gear * (force_needed - force)), 0.0)
    return ctrl, excess, saturated


def torque_headroom(xp, robot_arrays, q, v, actuator_force):
    """``(applied, box)``: the shielded actuators' joint torque in a solved substep ``(n,)`` [N m or N]
    (``shielded_torque``) and ``box = (lo, hi)``, the torque change they can still add at ``(q, v)``
    (``robot.torque_range`` less ``applied``): the boxed contact correction's box."""
    applied = shielded_torque(xp, robot_arrays, actuator_force)
    lo, hi = torque_range(xp, robot_arrays, q, v)
    return applied, (lo - applied, hi - applied)


def _boxed_inversion(xp, robot_arrays, M_eff, q, v, applied, fix):
    """``(ctrl, torque_excess, saturated)`` realising the boxed correction ``fix`` (a ``Correction``) on top of
    ``applied`` (``torque_headroom``): a torque inside the box asks no more than the actuators have, so it saturates
    only where no torque in the box meets the band, lacking (counted at the joints' own inertia ``M_eff,ss``, an
    estimate) what the predicted miss would take."""
    dofs = robot_arrays[0]
    ctrl = _invert(xp, robot_arrays, M_eff, None, None, q, v, False, tau=applied + fix.dtau)[0]
    saturated = fix.miss != 0
    excess = xp.where(saturated, xp.abs(sub_block(M_eff, dofs, dofs) @ fix.miss), 0.0)
    return ctrl, excess, saturated


def band_excess(xp, r, lo, hi):
    """``(n,)`` how far ``r`` lies outside ``[lo, hi]`` [rad/s^2], signed (positive above ``hi``, negative below ``lo``,
    0 inside): the push a contact correction undoes (``xp`` = ``jnp`` or ``numpy``)."""
    return r - clamp(xp, r, lo, hi)


def contact_response(xp, dofs, M, M_eff, J, D_active):
    """``(G, H_inv)``: ``G`` ``(n, n)`` the change of the shielded dofs' realised acceleration per unit torque
    added on them, ``G = [M_eff^-1 M H^-1]_ss``, ``H = M + J^T diag(D_active) J`` (the constraint solver's
    Hessian; exact while its active rows do not change), and ``H^-1`` ``(nv, nv)``. Arguments as
    ``contact_correction``."""
    H_inv = xp.linalg.inv(M + (J.T * D_active[None, :]) @ J)
    return sub_block(xp.linalg.solve(M_eff, M @ H_inv), dofs, dofs), H_inv


def _boxed_qp(G, h, t_lo, t_hi, scale):
    """``contact_correction``'s torque change ``(n,)``: the least ``dtau`` (each relative to ``scale``) in
    ``[t_lo, t_hi]`` with ``[G; -G] dtau <= h`` (``(2n,)``), met with least violation where no box point does."""
    rows = jnp.concatenate([G, -G], axis=0)
    return jl.solve_box_qp(jnp.zeros_like(t_lo), t_lo, t_hi, 1.0 / scale**2, G=rows, h=h).x


_boxed_qp_jit = jax.jit(_boxed_qp)


class Correction(NamedTuple):
    """``contact_correction``'s answer, ``(n,)`` each but ``dqacc``."""

    dtau: jax.Array  # [N m] the torque change
    out: jax.Array  # [rad/s^2] the excess over the band before it (0 inside)
    dqacc: jax.Array  # (nv,) the change of the solver's qacc it predicts, H^-1 dtau (the second solve's warm start)
    miss: jax.Array  # [rad/s^2] the excess over the band it predicts after it (0: met; torque_box only, else 0)


def contact_correction(xp, dofs, M, M_eff, J, D_active, qfrc, band, torque_box=None, inset=None) -> Correction:
    """The torque change ``(n,)`` [N m] bringing the shielded dofs' realised acceleration back into ``band``
    (module docstring): ``M`` ``(nv, nv)`` the mass matrix the constraint solver used, ``J`` ``(nefc, nv)``,
    ``D_active`` ``(nefc,)`` the active rows' impedance (0 elsewhere), ``qfrc`` ``(nv,)`` qfrc_smooth +
    qfrc_constraint of the solved substep. Returns a ``Correction``. A singular response (no finite answer)
    gives ``dtau = 0``.

    ``torque_box = (dtau_lo, dtau_hi)`` ``(n,)`` each: the torque change the actuators can still
    add (``±inf`` where unbounded). Then ``dtau`` is the least change (relative to each range) inside that box that
    puts every shielded dof's acceleration inside the band, ``lo - r <= G dtau <= hi - r``: the dofs already
    inside may move within it, so a joint whose motor is too weak to hold a contact's push is relieved by the
    others (pushing less into the contact); where no torque in the box does it, the box holds and the band is
    missed least (``jl.solve_box_qp``; ``miss`` then says by how much). Without it, ``dtau = -G^-1 out`` (the
    others' accelerations kept): exact where ``G`` is well conditioned, but where a stiff contact row makes it
    nearly singular (a ball pressed on a frictionless wall) that torque is large, pulls the body off the contact
    the response assumed active, and the joints take it (the wall task: 41 velocity-violating steps in 12 800,
    0 with the box).

    ``inset`` ``(n,)`` [rad/s^2] (MJX): a dof pushed out of the band by more than ``inset`` is aimed this far inside
    its edge (at most half the band's width), so that the residual of an inexact solve does not leave it; ``out``
    is still measured from the edge, and a dof inside the band stays where it is."""
    r = xp.linalg.solve(M_eff, qfrc)[dofs]
    lo, hi = band
    out = band_excess(xp, r, lo, hi)
    target_lo, target_hi = lo, hi
    if inset is not None:
        # only a push beyond the inset: roundoff at the edge (the decision's own answer) stays a correction to it
        inset = xp.minimum(inset, 0.5 * (hi - lo))
        target_lo = lo + xp.where(out < -inset, inset, 0.0)
        target_hi = hi - xp.where(out > inset, inset, 0.0)
    G, H_inv = contact_response(xp, dofs, M, M_eff, J, D_active)
    if torque_box is None:
        dtau = -xp.linalg.solve(G, band_excess(xp, r, target_lo, target_hi))
    else:
        t_lo, t_hi = xp.minimum(torque_box[0], 0.0), xp.maximum(torque_box[1], 0.0)
        width = t_hi - t_lo
        finite = xp.isfinite(width)
        widest = xp.max(xp.where(finite, width, 0.0))
        # an unbounded actuator: weighed as the widest bounded one, boxed far beyond any torque the actuators have
        scale = xp.maximum(xp.where(finite, width, widest), 1e-9)
        reach = 1e6 * (1.0 + widest)
        t_lo, t_hi = xp.maximum(t_lo, -reach), xp.minimum(t_hi, reach)
        # the band widened by the roundoff of r (~1e-6 relative in float32): a dof inside it stays inside
        eps = 8 * np.finfo(r.dtype).eps
        tol = eps * (1.0 + xp.abs(xp.concatenate([hi, lo])))
        h = xp.concatenate([target_hi - r, r - target_lo]) + tol
        if xp is np:  # C MuJoCo: the QP compiled once per size, in float64 as the rest, run where a contact pushed
            with jax.enable_x64(True):
                dtau = np.asarray(_boxed_qp_jit(G, h, t_lo, t_hi, scale), np.float64)
        else:
            dtau = _boxed_qp(G, h, t_lo, t_hi, scale)
    ok = xp.all(xp.isfinite(dtau)) & xp.any(out != 0)
    dtau = xp.where(ok, dtau, 0.0)
    if torque_box is None:
        miss = xp.zeros_like(r)
    else:
        # met where inside the band widened by the QP's tolerance and roundoff
        n = r.shape[0]
        slack = eps * (xp.abs(r) + xp.abs(G) @ xp.abs(dtau))
        miss = xp.where(ok, band_excess(xp, r + G @ dtau, lo - tol[n:] - slack, hi + tol[:n] + slack), out)
    return Correction(dtau, out, H_inv[:, dofs] @ dtau, miss)


def tree_dof_mask(model, dof_adr) -> np.ndarray:
    """``(nv,)`` bool: the dofs of the kinematic trees holding the dofs ``dof_adr`` (``model``: ``mujoco.MjModel``
    or ``mjx.Model``). ``M`` is block-diagonal over trees: a constraint row touching none of them cannot move
    those dofs."""
    treeid = np.asarray(model.dof_treeid)
    return np.isin(treeid, treeid[np.asarray(dof_adr)])


def other_rows_on_trees(model, robot: Robot) -> bool:
    """Whether ``model`` (``mujoco.MjModel`` or ``mjx.Model``) has constraint rows, other than contacts and the
    shielded joints' own limit rows, that can act on the shielded joints' kinematic trees: an unshielded limited
    joint there (Brax's inverted pendulum: its pole's hinge, coupled to the shielded cart through ``M``), an
    equality, friction loss on a tree dof, a limited tendon. The substep's correction then runs as for a
    contact (static: decided once per model)."""
    on_trees = tree_dof_mask(model, robot.dof_adr)
    jnt_on_trees = on_trees[np.asarray(model.jnt_dofadr)]
    shielded = np.isin(np.arange(len(jnt_on_trees)), np.asarray(robot.joint_ids))
    limited = np.asarray(model.jnt_limited).astype(bool) & ~shielded & jnt_on_trees
    friction = np.asarray(model.dof_frictionloss)[on_trees] > 0
    return bool(limited.any() or int(model.neq) or friction.any() or np.asarray(model.tendon_limited).any())


RK4_PASSES = 3  # C MuJoCo, RK4: substeps retaken with the realised excess (CActuation._rk4_step_in_band)
# MJX: correction passes per substep where the shielded joints share a kinematic tree with unshielded dofs (a floating
# or planar base on its feet; one pass elsewhere: MjxActuation.finish_substep), and the fewest constraint-solver
# iterations the shielded substeps run (Brax's ant and humanoid run 1)
MJX_CORRECTION_PASSES = 2
MJX_MIN_SOLVER_ITERATIONS = 4
# MJX (float32): a correction aims this far [a_max] inside the band's edge, so that the residual of the passes does
# not leave it (Brax ant at XLA's -O0: one step of 3 200 3.7e-6 rad over, aimed at the edge)
MJX_CORRECTION_INSET = 1e-4
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


def _with_min_iterations(sys):
    """``sys`` with ``opt.iterations`` raised to ``MJX_MIN_SOLVER_ITERATIONS`` where it is lower."""
    if int(sys.opt.iterations) < MJX_MIN_SOLVER_ITERATIONS:
        return sys.tree_replace({"opt.iterations": MJX_MIN_SOLVER_ITERATIONS})
    return sys


class MjxActuation:
    """The substep pieces of ``mjx.step`` with the shielded actuators' ``ctrl`` set between the velocity
    and the actuation stages (Euler, implicitfast, RK4: the model's own integrator). ``sys.opt.iterations``
    is raised to ``MJX_MIN_SOLVER_ITERATIONS`` where it is lower (``self.sys``; module docstring)."""

    def __init__(self, robot: Robot, sys):
        self.robot = robot
        self._given = self._structure = sys
        self.sys = _with_min_iterations(sys)
        f32 = np.float32
        self._arrays = (
            np.asarray(robot.dof_adr),
            np.asarray(robot.other_dofs),
            robot.gear.astype(f32),
            robot.gain.astype(f32),
            robot.bias.astype(f32),
            robot.ctrl_range.astype(f32),
            robot.force_range.astype(f32),
        )
        self._damping = (robot.timestep * np.asarray(_implicit_damping(sys, xp=np, engine="mjx"))).astype(f32)
        self._stiff = (0.5 * robot.timestep * robot.rk4_stiffness).astype(f32)
        self._act = np.asarray(robot.actuator_ids)
        self._other_rows = other_rows_on_trees(sys, robot)
        self._passes = MJX_CORRECTION_PASSES if robot.coupled else 1
        self._inset = (MJX_CORRECTION_INSET * np.broadcast_to(robot.limits.a_max, (robot.n,))).astype(f32)
        integ = int(sys.opt.integrator)
        self._integrate = {
            int(mujoco.mjtIntegrator.mjINT_EULER): mjx_stages.euler,
            int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST): mjx_stages.implicit,
            int(mujoco.mjtIntegrator.mjINT_RK4): mjx.rungekutta4,
        }[integ]

    def with_system(self, sys) -> "MjxActuation":
        """This actuation over ``sys``, the System the env steps with now: ``self`` where it is the one given at
        construction, else a copy whose substeps run ``sys`` (iterations raised as in ``__init__``) and whose
        actuator gains, ranges, implicit damping and RK4 stiffness are read from it (traced values under Brax's
        ``DomainRandomizationVmapWrapper``, which sets a randomised System on the innermost env inside its
        ``vmap``; before, the shielded substeps ran the System captured at construction and a domain randomisation
        reached neither the physics nor the shield). The structure (which actuators, the integrator, the static
        choice of ``other_rows_on_trees``) and the robot's limits stay those of construction."""
        if sys is self._given:
            return self
        new = copy.copy(self)
        new._given, new.sys = sys, _with_min_iterations(sys)
        new._arrays = self._arrays[:2] + actuator_arrays(
            jnp, self._structure, sys, self.robot.actuator_ids, jnp.float32
        )
        h = self.robot.timestep
        new._damping = (h * _implicit_damping(self._structure, sys, jnp, "mjx")).astype(jnp.float32)
        new._stiff = (0.5 * h * _rk4_stiffness(self._structure, sys, jnp)).astype(jnp.float32)
        return new

    def smooth_stage(self, d, ctrl):
        """Positions, velocities, actuation and smooth acceleration at ``d``'s state with the env's ``ctrl``.

        Returns ``(d, M_eff, f_other)``, ``M_eff`` ``(nv, nv)``; the acceleration ``ctrl`` asks of the shielded
        joints is ``asked_acceleration(d, M_eff)`` (only a step's first substep needs it).
        """
        sys = self.sys
        d = d.replace(ctrl=jnp.asarray(ctrl, d.ctrl.dtype))  # the state's dtype: a scan carries it
        d = mjx_stages.fwd_position(sys, d)
        d = mjx_stages.sensor_pos(sys, d)
        d = mjx_stages.fwd_velocity(sys, d)
        d = mjx_stages.sensor_vel(sys, d)
        d = mjx_stages.fwd_actuation(sys, d)
        d = mjx_stages.fwd_acceleration(sys, d)
        M_eff = mjx_stages.full_m(sys, d) + jnp.asarray(self._damping, d.qvel.dtype)
        dofs = self._arrays[0]
        f_env = d.qfrc_smooth
        f_other = (
            f_env.at[dofs].add(-shielded_torque(jnp, self._arrays, d.actuator_force[self._act])) - self._stiff * d.qvel
        )
        return d, M_eff, f_other

    def mass(self, M_eff):
        """``(nv, nv)`` the mass matrix ``M`` (armature included) from ``smooth_stage``'s ``M_eff = M + h D``."""
        return M_eff - jnp.asarray(self._damping, M_eff.dtype)

    def asked_acceleration(self, d, M_eff):
        """``a_des`` ``(n,)``: the acceleration the env's ``ctrl`` asks of the shielded joints under the
        integrator, ``M_eff^-1 qfrc_smooth`` (after ``smooth_stage``)."""
        return jnp.linalg.solve(M_eff, d.qfrc_smooth)[self._arrays[0]]

    def torque_model(self, d, M_eff, f_other, dt: float) -> TorqueModel:
        """The ``TorqueModel`` at ``d``'s state (after ``smooth_stage``), for a step of ``dt`` [s]."""
        dofs = self._arrays[0]
        a_max = jnp.asarray(self.robot.limits.a_max, d.qvel.dtype)
        lo, hi = torque_range(jnp, self._arrays, d.qpos[self.robot.qpos_adr], d.qvel[dofs], dt, a_max)
        return TorqueModel(*joint_dynamics(jnp, M_eff, f_other, dofs, None, False), *shrink(lo, hi))

    def _constraint_stage(self, d, ctrl):
        """Actuation, smooth acceleration and the constraint solve at ``d``'s state with the shielded ``ctrl``."""
        sys = self.sys
        d = d.replace(ctrl=d.ctrl.at[self._act].set(ctrl))
        d = mjx_stages.fwd_actuation(sys, d)
        d = mjx_stages.fwd_acceleration(sys, d)
        # mjx.forward's own test for "no constraint rows" (a shape, static under jit)
        if d._impl.efc_J.size == 0:
            return d.replace(qacc=d.qacc_smooth)
        return mjx_stages.sensor_acc(sys, mjx_stages.solve(sys, d))

    def finish_substep(self, d, M_eff, f_other, a, band=None):
        """Set the shielded ctrl realising ``a`` ``(n,)``, then actuation, constraints and the integrator;
        with ``band = (lower, upper)`` ``(n,)`` each and contacts in the model, the contact correction
        (module docstring).

        Returns ``(d, inversion, out)``: ``out`` the excess of the uncorrected realised acceleration over
        the band [rad/s^2] (``(n,)``, zeros without correction). Corrected, the inversion realises the boxed
        correction's torque, and ``saturated`` / ``torque_excess`` say where no torque the actuators have meets the
        band (``_boxed_inversion``). ``MJX_CORRECTION_PASSES`` corrections, each from the last solve's rows, aimed
        ``MJX_CORRECTION_INSET`` a_max inside the band, where ``robot.coupled`` (a floating or planar base: its feet's contact rows change with the torque), else one
        (a fixed base: Brax ``pusher``'s strikes are saturations a second pass does not fix, 18 -> 16 violating
        steps of 3 200, at +40 % of its step at batch 256: under ``vmap`` every member pays every pass).
        """
        dofs = self._arrays[0]
        q, v = d.qpos[self.robot.qpos_adr], d.qvel[dofs]

        inv = Inversion(*_invert(jnp, self._arrays, M_eff, f_other, a, q, v, self.robot.coupled))
        dc = self._constraint_stage(d, inv.ctrl)
        out = jnp.zeros_like(a)
        first = inv
        # contacts (a static size) or other rows that reach the shielded trees (other_rows_on_trees): the shield
        # keeps its joints off their own limits' rows, and a model without either pays nothing
        if band is not None and (d._impl.ncon or self._other_rows) and self._integrate is not mjx.rungekutta4:
            # passes: a correction that makes or breaks a contact row is corrected again from the new rows
            M = mjx_stages.full_m(self.sys, dc)
            inset = jnp.asarray(self._inset, a.dtype)
            for k in range(self._passes):
                impl = dc._impl
                D_active = jnp.where(impl.efc_force != 0, impl.efc_D, 0.0)
                qfrc = dc.qfrc_smooth + dc.qfrc_constraint
                applied, box = torque_headroom(jnp, self._arrays, q, v, dc.actuator_force[self._act])
                fix = contact_correction(jnp, dofs, M, M_eff, impl.efc_J, D_active, qfrc, band, box, inset)
                if k == 0:  # the push as the shield's ctrl met it (the metric); later passes correct its residual
                    out = fix.out
                inv = Inversion(*_boxed_inversion(jnp, self._arrays, M_eff, q, v, applied, fix))
                # warm-started at the predicted answer: the solver's loop (run until a batch's slowest member is
                # done) then stops after an iteration or two
                dc = self._constraint_stage(d.replace(qacc_warmstart=dc.qacc + fix.dqacc), inv.ctrl)
            # where the realised acceleration lay inside the band (no correction needed: the boxed torque change is
            # nil), the actuators' clamps are the first inversion's, as C MuJoCo reports them (CActuation); the
            # boxed inversion's miss, relative to the band, would hide a clamp that the band happens to contain
            # (the decided acceleration not realised: a torque-blind decision, an impact cap's row)
            needed = jnp.any(out != 0)
            inv = Inversion(
                inv.ctrl,
                jnp.where(needed, inv.torque_excess, first.torque_excess),
                jnp.where(needed, inv.saturated, first.saturated),
            )
        return self._integrate(self.sys, dc), inv, out


class CActuation:
    """The same substep over C MuJoCo (``mj_step1`` / ctrl / ``mj_step2``; RK4: a full ``mj_step``)."""

    def __init__(self, robot: Robot, model: mujoco.MjModel):
        self.robot = robot
        self.model = model
        self._arrays = (
            as_slice(robot.dof_adr),
            np.asarray(robot.other_dofs),
            robot.gear,
            robot.gain,
            robot.bias,
            robot.ctrl_range,
            robot.force_range,
        )
        self._structure = mujoco.MjModel.__copy__(model)  # which actuators have a bias, the integrator, the flags
        self._damping = robot.timestep * robot.implicit_damping
        self._stiff = 0.5 * robot.timestep * robot.rk4_stiffness
        self._rk4 = model.opt.integrator == mujoco.mjtIntegrator.mjINT_RK4
        self._state = np.empty(mujoco.mj_stateSize(model, _STATE))  # an RK4 substep's start (_rk4_step_in_band)
        self._other_rows = other_rows_on_trees(model, robot)
        self._passes = MJX_CORRECTION_PASSES if robot.coupled else 1  # as MJX's (Euler, implicitfast)
        self._M = np.zeros((model.nv, model.nv))
        self._zero_n = np.zeros(robot.n)
        self._zero_n.flags.writeable = False
        self._act = as_slice(robot.actuator_ids)
        self._dofs = self._arrays[0]
        self._qadr = as_slice(robot.qpos_adr)
        # the dofs of the kinematic trees holding the shielded joints (a row touching none cannot move them)
        self._tree_dofs = as_slice(np.flatnonzero(tree_dof_mask(model, robot.dof_adr)))

    def refresh(self) -> None:
        """Re-read the actuators' gains, bias, ranges, the implicit damping and the RK4 stiffness from the live
        ``model`` (a domain randomisation that changes them between episodes; the wrapper calls this at every
        ``reset``). Masses and armature need nothing: ``M`` is the live model's at every substep. The robot's limits,
        ``a_max`` included, stay those of construction."""
        m, h = self.model, self.robot.timestep
        self._arrays = self._arrays[:2] + actuator_arrays(np, self._structure, m, self.robot.actuator_ids, np.float64)
        self._damping = h * _implicit_damping(self._structure, m)
        self._stiff = 0.5 * h * _rk4_stiffness(self._structure, m)

    def smooth_stage(self, d: mujoco.MjData, ctrl: np.ndarray, want_a_des: bool = True):
        """As ``MjxActuation.smooth_stage`` (``d`` is changed in place) and ``asked_acceleration``; returns
        ``(a_des, M_eff, f_other)``.

        ``want_a_des=False`` skips the solve for ``a_des`` (``None``): only a step's first substep needs it."""
        m = self.model
        d.ctrl[:] = ctrl
        if self._rk4:
            mujoco.mj_fwdPosition(m, d)
            mujoco.mj_fwdVelocity(m, d)
        else:
            mujoco.mj_step1(m, d)
        mujoco.mj_fwdActuation(m, d)
        mujoco.mj_fwdAcceleration(m, d)
        mujoco.mj_fullM(m, d, self._M)
        M_eff = self._M
        M_eff += self._damping
        f_env = d.qfrc_smooth
        f_other = f_env.copy()
        f_other[self._dofs] -= shielded_torque(np, self._arrays, d.actuator_force[self._act])
        if self._rk4:
            f_other -= self._stiff * d.qvel
        a_des = np.linalg.solve(M_eff, f_env)[self._dofs] if want_a_des else None
        return a_des, M_eff, f_other

    def torque_model(self, d: mujoco.MjData, M_eff, f_other, dt: float) -> TorqueModel:
        """As ``MjxActuation.torque_model`` (NumPy float64)."""
        dofs = self._dofs
        lo, hi = torque_range(
            np, self._arrays, d.qpos[self._qadr], d.qvel[dofs], dt, np.asarray(self.robot.limits.a_max)
        )
        return TorqueModel(*joint_dynamics(np, M_eff, f_other, dofs, None, False), *shrink(lo, hi))

    def finish_substep(self, d: mujoco.MjData, M_eff, f_other, a, band=None, rk4_tol=0.0):
        """As ``MjxActuation.finish_substep`` (``d`` advanced in place); returns ``(inversion, out)``, ``out``
        ``(n,)`` the excess of the uncorrected realised acceleration over the band [rad/s^2], or ``None`` where
        it lay inside (C MuJoCo runs the check only in substeps with constraint rows on the shielded joints'
        kinematic trees, ``_rows_touch_trees``)."""
        m = self.model
        q, v = d.qpos[self._qadr], d.qvel[self._dofs]
        ctrl, excess, sat = _invert(np, self._arrays, M_eff, f_other, a, q, v, self.robot.coupled)
        d.ctrl[self._act] = ctrl
        out, dtau, rows = None, self._zero_n, None
        if band is not None and (d.ncon or self._other_rows) and self._rows_touch_trees(d):
            # where the shielded joints share a chain with unshielded dofs (a floating base, a gripper's fingers
            # against their limits) the corrected torque makes or breaks rows: corrected again from the rows it
            # met, as MJX does (RK4: one pass, then the retakes of _rk4_step_in_band)
            # Euler/implicitfast: the last correction is solved once more and the best torque evaluated is kept (a
            # correction against a stiff contact can make it worse: its near-singular response asks far more than
            # the actuators have, and clamped per actuator that torque no longer corrects)
            passes = 1 if self._rk4 else self._passes
            best = None  # (how far r left the band, ctrl, excess, sat)
            for k in range(passes + (not self._rk4)):
                mujoco.mj_fwdActuation(m, d)
                mujoco.mj_fwdAcceleration(m, d)
                mujoco.mj_fwdConstraint(m, d)
                qfrc = d.qfrc_smooth + d.qfrc_constraint
                r = np.linalg.solve(M_eff, qfrc)[self._dofs]
                miss = float(np.abs(band_excess(np, r, *band)).max())
                if best is None or miss < best[0]:
                    best = (miss, ctrl, excess, sat)
                outside = miss > 0.0
                if k == 0 and (outside or self._rk4):
                    # the start's constraint rows (a copy of efc_J for RK4: the step overwrites it, and a retake
                    # may need their response, _rk4_step_in_band)
                    J = self._efc_jacobian(d)
                    rows = (self._full_m(d), J.copy() if self._rk4 else J, self._efc_d_active(d))
                if not outside or k == passes:
                    break
                J, D_active = (rows[1], rows[2]) if k == 0 else (self._efc_jacobian(d), self._efc_d_active(d))
                box = None
                if not self._rk4:  # boxed, as MJX's (RK4's retakes build on the unboxed dtau)
                    applied, box = torque_headroom(np, self._arrays, q, v, d.actuator_force[self._act])
                fix = contact_correction(np, self._dofs, rows[0], M_eff, J, D_active, qfrc, band, box)
                if k == 0:  # the push as the shield's ctrl met it (the metric); later passes correct its residual
                    out = fix.out
                d.qacc_warmstart[:] = d.qacc + fix.dqacc
                if box is None:
                    dtau = dtau + fix.dtau
                    ctrl, excess, sat = _invert(np, self._arrays, M_eff, f_other, a, q, v, self.robot.coupled, dtau)
                else:
                    ctrl, excess, sat = _boxed_inversion(np, self._arrays, M_eff, q, v, applied, fix)
                d.ctrl[self._act] = ctrl
            if not self._rk4 and best[1] is not ctrl:  # a correction made it worse: the best torque evaluated
                _, ctrl, excess, sat = best  # (dtau is read after this only by RK4)
                d.ctrl[self._act] = ctrl
        if self._rk4 and band is not None:
            inv = Inversion(ctrl, excess, sat)
            return self._rk4_step_in_band(d, M_eff, f_other, a, q, v, band, dtau, rows, rk4_tol, inv), out
        if self._rk4:
            mujoco.mj_step(m, d)
        else:
            mujoco.mj_step2(m, d)
        return Inversion(ctrl, excess, sat), out

    def _rk4_step_in_band(self, d: mujoco.MjData, M_eff, f_other, a, q, v, band, dtau, rows, rk4_tol, inv) -> Inversion:
        """An RK4 substep with a band. RK4 holds ``ctrl`` over four stages whose constraint forces differ from the
        first stage's (the one the correction solved; a contact may even start within the substep), so the step
        is taken and its realised acceleration ``(v+ - v) / h`` read; where that left the band by more than
        ``rk4_tol`` [rad/s^2] (scalar or ``(n,)``; ``joint_shield.RK4_RESTEP``), the step is taken
        again from the same state (``mj_getState``/``mj_setState``) with the torque moved by the realised excess,
        through the response ``G`` (``contact_response``: the first stage's contacts, else the last stage's,
        else the smooth ``[M_eff^-1]_ss``; Broyden's update from the passes after), at most ``RK4_PASSES``
        times (``inv``: the first pass's commands, for ``dtau``; ``rows``: ``(M, efc_J, D_active)`` of the first
        stage's constraint rows on the shielded trees, or ``None``; ``G`` is formed only for a retake), keeping
        the best pass (a pass that is no better, e.g. saturated, ends it). Without contacts this corrects RK4's
        own deviation from the held acceleration (``ctrl`` held over the stages; joint damping fast against the
        substep: Gymnasium's Ant left the band by up to ~10 rad/s^2)."""
        m, h = self.model, self.robot.timestep
        spec, state = _STATE, self._state
        mujoco.mj_getState(m, d, state, spec)
        lo, hi = band
        v = v.copy()
        best = prev = tol = G = None
        for k in range(RK4_PASSES + 1):
            d.ctrl[self._act] = inv.ctrl
            mujoco.mj_step(m, d)
            r = (d.qvel[self._dofs] - v) / h
            out = band_excess(np, r, lo, hi)
            err = float(np.max(np.abs(out)))
            if k == 0 and err == 0.0:  # inside the band: the common case
                return inv
            if tol is None:
                tol = np.maximum(rk4_tol, 1e-9 * (1.0 + np.maximum(np.abs(lo), np.abs(hi))))
            if best is not None and not err < best[0]:  # no better (saturated, or the response changed): the best
                mujoco.mj_setState(m, d, state, spec)
                d.ctrl[self._act] = best[1].ctrl
                mujoco.mj_step(m, d)
                return best[1]
            best = (err, inv)
            if k == RK4_PASSES or not np.any(np.abs(out) > tol):
                break
            if G is None and rows is not None:  # the first stage's constraint rows
                G = contact_response(np, self._dofs, rows[0], M_eff, rows[1], rows[2])[0]
            elif G is None and d.ncon and self._rows_touch_trees(d):  # a contact began within the substep
                M_end = self._full_m(d)
                M_eff_end = M_end + self._damping
                G = contact_response(np, self._dofs, M_end, M_eff_end, self._efc_jacobian(d), self._efc_d_active(d))[0]
            elif G is None:  # none: the smooth response
                G = sub_block(np.linalg.inv(M_eff), self._dofs, self._dofs)
            if prev is not None:  # Broyden's update of the response from the last two passes
                s_, y_ = dtau - prev[0], r - prev[1]
                ss = float(s_ @ s_)
                if ss > 0:
                    G = G + np.outer(y_ - G @ s_, s_) / ss
            prev = (dtau.copy(), r.copy())
            try:
                step = np.linalg.solve(G, out)
            except np.linalg.LinAlgError:  # an exactly singular response: keep this pass
                break
            if not np.all(np.isfinite(step)):
                break
            dtau = dtau - step
            mujoco.mj_setState(m, d, state, spec)
            inv = Inversion(*_invert(np, self._arrays, M_eff, f_other, a, q, v, self.robot.coupled, dtau))
        return inv

    def _rows_touch_trees(self, d: mujoco.MjData) -> bool:
        """Whether a constraint row of ``d`` (made by ``mj_step1``) has a Jacobian entry on the shielded joints'
        trees. Where none has, the constraint forces leave the shielded dofs' acceleration exactly as without
        them (e.g. Pusher-v5's object resting on its table), and the check is skipped: as in a model without
        contacts, the realised acceleration is the inversion's."""
        return bool(d.nefc) and bool(self._efc_jacobian(d)[:, self._tree_dofs].any())

    def _full_m(self, d: mujoco.MjData) -> np.ndarray:
        M = np.zeros((self.model.nv, self.model.nv))
        mujoco.mj_fullM(self.model, d, M)
        return M

    def _efc_jacobian(self, d: mujoco.MjData) -> np.ndarray:
        """``efc_J`` ``(nefc, nv)``, dense (C MuJoCo keeps it sparse for large models)."""
        m, nefc = self.model, d.nefc
        if not mujoco.mj_isSparse(m):
            return d.efc_J[: nefc * m.nv].reshape(nefc, m.nv)
        J = np.zeros((nefc, m.nv))
        mujoco.mju_sparse2dense(J, d.efc_J, d.efc_J_rownnz[:nefc], d.efc_J_rowadr[:nefc], d.efc_J_colind)
        return J

    @staticmethod
    def _efc_d_active(d: mujoco.MjData) -> np.ndarray:
        """The impedance of the rows in the solver's quadratic (active) zone (cone rows counted with them)."""
        state = d.efc_state[: d.nefc]
        active = (state == mujoco.mjtConstraintState.mjCNSTRSTATE_QUADRATIC) | (
            state == mujoco.mjtConstraintState.mjCNSTRSTATE_CONE
        )
        return np.where(active, d.efc_D[: d.nefc], 0.0)
