"""Joint-acceleration actions for a fixed-base robot MJCF: the ``ctrl`` that asks the integrator for ``action * scale``.

The project's own arms (``ArmReach``) take joint accelerations as actions, the paper's setting; a robot's own
actuators take ``ctrl``. ``AccelerationActions`` maps one onto the other at a step's start state, so that a task over
any robot (``reach.Reach(action="acceleration")``) offers the same action space as ``ArmReach`` and runs under the
one shield, ``JointLimitShield``, whose decision then sees the acceleration the policy asked for:

    a = action * scale                                      [rad/s^2 or m/s^2], (nu,) in actuator order
    tau = [M_eff a_full - f_other]_dofs                     M_eff = M + h D (the integrator's implicit damping)
    ctrl = (tau / gear - b0 - b1 gear q - b2 gear v) / gain  (``actuation._invert``; clamped to ``ctrlrange``)

with ``f_other = qfrc_smooth - qfrc_actuator`` (gravity, Coriolis, springs, damping, applied forces) at the state.
The shield reads the acceleration a ``ctrl`` asks as ``M_eff^-1 qfrc_smooth`` (``MjxActuation.asked_acceleration``),
which is then ``a`` exactly where no range clamps the actuator (a clamp is the actuator's saturation, as for any
``ctrl``). Unshielded, ``ctrl`` is held over the step's substeps (Brax's ``pipeline_step``), so only the first substep
realises ``a`` exactly; under ``JointLimitShield`` every substep realises the decided acceleration.

Needs every dof driven by exactly one actuator of the kinds ``Robot`` supports (``robot.SUPPORTED_ACTUATORS``: motors
of any gear, position servos, ``general`` with fixed gain and affine bias), each on its own hinge or slide joint;
anything else is an eager ``ValueError`` naming the actuator or the joint.
"""

from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np

from jaxlimits.envs import mjx_stages
from jaxlimits.envs.actuation import _invert
from jaxlimits.envs.arm import _mjx_tracing
from jaxlimits.envs.robot import (
    _SHIELDABLE,
    _TRN_JOINT,
    _check_actuator,
    _implicit_damping,
    _name,
    _numeric,
    actuator_arrays,
    actuators_by_joint,
)


class AccelerationActions:
    """``ctrl(sys, d, action)``: the actuators' ``ctrl`` asking for the joint acceleration ``action * scale``.

    Args:
      sys: the model (``mjx.Model`` or a Brax ``System``; its ``mj_model`` is read for the structure).
      scale: [rad/s^2 or m/s^2] per unit action, scalar or per actuator (``(nu,)``, finite, > 0); default the MJCF
        custom numeric ``jaxlimits_a_max`` (per joint), else a ``ValueError``.
    """

    def __init__(self, sys, scale=None):
        mjm = sys.mj_model
        nu, nv = int(mjm.nu), int(mjm.nv)
        joints = np.asarray(mjm.actuator_trnid)[:, 0]
        for a in range(nu):
            an = _name(mjm, mujoco.mjtObj.mjOBJ_ACTUATOR, a)
            if int(mjm.actuator_trntype[a]) != _TRN_JOINT or int(mjm.jnt_type[joints[a]]) not in _SHIELDABLE:
                raise ValueError(f"acceleration actions: actuator {an!r} does not drive a hinge or slide joint")
            _check_actuator(mjm, a)
        driven = actuators_by_joint(mjm)
        counts = [len(driven.get(j, ())) for j in range(int(mjm.njnt))]
        if nu != nv or any(c != 1 for c in counts):
            bad = {_name(mjm, mujoco.mjtObj.mjOBJ_JOINT, j): c for j, c in enumerate(counts) if c != 1}
            raise ValueError(
                "acceleration actions need every dof driven by exactly one actuator; joints {name: actuators "
                f"driving it}}: {bad}"
            )
        dofs = np.asarray(mjm.jnt_dofadr)[joints]
        if scale is None:
            per_joint = _numeric(mjm, "jaxlimits_a_max", int(mjm.njnt))
            if per_joint is None:
                raise ValueError(
                    "acceleration actions need acceleration_scale (scalar or per actuator) or the MJCF custom numeric "
                    "jaxlimits_a_max"
                )
            scale = per_joint[joints]
        scale = np.broadcast_to(np.asarray(scale, np.float64), (nu,)).copy()
        if not np.all(np.isfinite(scale) & (scale > 0)):
            raise ValueError(f"acceleration_scale must be finite and > 0, got {scale.tolist()}")
        self.scale = scale
        self._structure = sys  # which actuators have a bias, which ranges are limited, the integrator, the flags
        self._dofs = dofs
        self._qadr = np.asarray(mjm.jnt_qposadr)[joints]

    @_mjx_tracing
    def ctrl(self, sys, d, action):
        """``(nu,)`` the ``ctrl`` for ``action`` ``(nu,)`` at the positions and velocities of ``d`` (MJX data; its
        other fields may be stale: the stages are recomputed), clamped to ``ctrlrange``. The gains, biases, ranges
        and damping are read from ``sys``, the System the env steps with now (a domain randomisation's, traced), as
        ``MjxActuation.with_system`` reads them."""
        d = d.replace(ctrl=jnp.zeros_like(d.ctrl))
        d = mjx_stages.fwd_velocity(sys, mjx_stages.fwd_position(sys, d))
        d = mjx_stages.fwd_acceleration(sys, mjx_stages.fwd_actuation(sys, d))
        dtype = d.qvel.dtype
        damping = float(self._structure.opt.timestep) * _implicit_damping(self._structure, sys, jnp, "mjx")
        M_eff = mjx_stages.full_m(sys, d) + damping.astype(dtype)
        f_other = d.qfrc_smooth - d.qfrc_actuator
        a = jnp.asarray(action, dtype) * jnp.asarray(self.scale, dtype)
        nu = len(self._dofs)
        arrays = (self._dofs, np.zeros(0, np.intp)) + actuator_arrays(jnp, self._structure, sys, np.arange(nu), dtype)
        ctrl, _, _ = _invert(jnp, arrays, M_eff, f_other, a, d.qpos[self._qadr], d.qvel[self._dofs], False)
        return ctrl
