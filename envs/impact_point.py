"""The impact-aware speed cap (Wang & Kheddar 2019) for any MuJoCo model: the point that may strike, read from it.

    env = JointLimitShield(brax.envs.get_environment("pusher", backend="mjx"), v_max=2.0,
                           impact=ImpactPoint("tips_arm", normal=(0, 0, -1)))

``ImpactPoint`` names the point of the robot that may strike a surface (a site, else a body's origin) and the
direction it would strike in (``normal``: world frame, pointing *into* the surface; ``(0, 0, -1)`` for a floor or
a table below). Each control step the shield evaluates, at the step's start state, the shielded joints' mass
matrix ``M`` ``(n, n)`` and the point's translational Jacobian ``J`` ``(3, n)``, and from them the largest safe
approach speed ``cap`` [m/s] (``jaxlimits.impact.impact_speed_cap``: the predicted joint-velocity jumps keep the
position (16) and velocity (17) limits and the impulsive torques (20) ``tau_imp_max``), for every pre-impact
velocity ``v + dt [lower - a_max, upper + a_max]`` within ``±v_max`` (this step's bounds and what the next step
adds: a strike early in the next step comes at this step's end velocity). The cap enters the decision as one
halfspace row on the end-of-step speed, ``n̂ . J (v + a dt) <= margin cap``
(``jaxlimits.impact.speed_cap_halfspace``), beside the acceleration bounds and the torque rows. Where no command
inside the bounds and the actuators' torque range meets it, the bounds and the torques hold and the cap is exceeded
(``Decision.impact_excess`` [m/s], counted as ``shield/impact_infeasible``). The same model as the project's own
``WallStrike`` (``SafetyWrapper(impact=)``), without its task-consistent pre-correction: in the torque-space decision
the projection runs in Gauss's metric ``M``, whose correction direction for this row is already
``M^-1 J^T n̂``.

What the cap does not know (documented limits of the model): the surface's position (the cap applies wherever the
point is, approaching or not: it slows the point's motion along ``normal`` everywhere); the unshielded dofs (the
jumps are those of the shielded chain with the others held, as ``actuation.TorqueModel``); a strike by another
part of the robot than the named point.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
from mujoco import mjx
from mujoco.mjx._src import support as _mjx_support  # jac_dot: not re-exported by mjx 3.17
import numpy as np

import jaxlimits.impact as _impact
from jaxlimits.envs.content_cache import array_key


class ImpactPoint(NamedTuple):
    """Where and how the robot may strike (SI units).

    point: a site name of the model, else a body name (the body's origin).
    normal: ``(3,)`` world direction of approach, into the surface (normalised here; not zero).
    c_range: restitution range ``(c_min, c_max)``; the predictions use ``c_max``.
    dt_impact: impact duration [s] (Wang & Kheddar's 0.005 s).
    tau_imp_max: ``(n,)`` or scalar impulsive joint-torque bound [N m]; ``None``: each shielded actuator's peak joint
      torque (``peak_torque``: its ``forcerange``, else a motor's ``ctrlrange``, times its gear), as the project's
      ``WallStrike`` takes its motors' limits. A gearbox usually tolerates more for an impact's few milliseconds:
      pass your robot's figure.
    margin: the cap is scaled by it, in ``(0, 1]``.
    contact: a ``jaxlimits.impact.ContactModel``; ``None``: ``PaperContact()`` (frictionless, the paper's).
    enforce: ``True``: the cap is a row of the decision; ``False``: only measured (the cap and the approach speed are
      reported, the decision is the one without it: what a robot's strikes would be, against the cap).
    surface: ``None`` (the cap applies everywhere) or ``(3,)`` a point of the plane struck [m, world], normal to
      ``normal``: then the cap applies only where the point may reach the plane before it can be braked toward the
      cap (``ImpactModel.halfspace``): a robot far from the surface moves freely.
    clearance: [m] how far the striking geometry reaches past the point toward the surface (e.g. a capsule's radius
      and half-length around a body's origin), taken off the distance.
    window, stop_fraction: the strike measurement (``envs/strike_record.py``): a strike's window opens at the first
      physics substep in which a geom of the point's body (or of a body it carries) is in a contact, and closes once the
      point's approach speed has fallen below ``stop_fraction`` of its value then, at most ``window`` [s] later.
    """

    point: str
    normal: tuple = (0.0, 0.0, -1.0)
    c_range: tuple = (0.0, 0.2)
    dt_impact: float = 0.005
    tau_imp_max: object = None
    margin: float = 1.0
    contact: object = None
    enforce: bool = True
    surface: object = None
    clearance: float = 0.0
    window: float = 0.02
    stop_fraction: float = 0.1

    def resolve(self, mj_model: mujoco.MjModel, robot) -> "ImpactModel":
        """The checked, numeric form for ``robot`` (a ``Robot`` of ``mj_model``). Raises ``ValueError`` naming the
        field and value (an unknown point lists the model's sites and bodies)."""
        site = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, self.point) if self.point else -1
        body = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_BODY, self.point) if self.point else -1
        if site < 0 and body < 0:
            names = lambda kind, count: [mujoco.mj_id2name(mj_model, kind, i) for i in range(count)]  # noqa: E731
            raise ValueError(
                f"ImpactPoint.point {self.point!r} is neither a site nor a body of the model; sites: "
                f"{names(mujoco.mjtObj.mjOBJ_SITE, mj_model.nsite)}, bodies: {names(mujoco.mjtObj.mjOBJ_BODY, mj_model.nbody)}"
            )
        if site >= 0:
            body = int(mj_model.site_bodyid[site])
        if body == 0:
            raise ValueError(f"ImpactPoint.point {self.point!r} is on the world body: it cannot strike")
        normal = np.asarray(self.normal, np.float64)
        norm = float(np.linalg.norm(normal)) if normal.shape == (3,) else 0.0
        if not (np.isfinite(norm) and norm > 0):
            raise ValueError(f"ImpactPoint.normal must be a finite non-zero 3-vector, got {self.normal!r}")
        c_max = _impact.check_restitution(*self.c_range)
        if not float(self.dt_impact) > 0:
            raise ValueError(f"ImpactPoint.dt_impact must be > 0, got {self.dt_impact!r}")
        if not 0.0 < float(self.margin) <= 1.0:
            raise ValueError(f"ImpactPoint.margin must be in (0, 1], got {self.margin!r}")
        tau = np.asarray(peak_torque(robot) if self.tau_imp_max is None else self.tau_imp_max, np.float64)
        if tau.shape not in ((), (robot.n,)):
            raise ValueError(
                f"ImpactPoint.tau_imp_max must be a scalar or ({robot.n},) per joint, got shape {tau.shape}"
            )
        tau = np.broadcast_to(tau, (robot.n,)).copy()
        if not (np.all(np.isfinite(tau)) and np.all(tau > 0)):
            bad = {robot.names[i]: float(tau[i]) for i in np.flatnonzero(~(np.isfinite(tau) & (tau > 0)))}
            raise ValueError(f"ImpactPoint.tau_imp_max must be finite and > 0 per joint, got {bad}")
        contact = _impact.check_contact(_impact.PaperContact() if self.contact is None else self.contact)
        if not isinstance(self.enforce, bool):
            raise ValueError(f"ImpactPoint.enforce must be True or False, got {self.enforce!r}")
        surface = None if self.surface is None else np.asarray(self.surface, np.float64)
        if surface is not None and not (surface.shape == (3,) and np.all(np.isfinite(surface))):
            raise ValueError(f"ImpactPoint.surface must be None or a finite 3-vector, got {self.surface!r}")
        if not (np.isfinite(float(self.clearance)) and float(self.clearance) >= 0):
            raise ValueError(f"ImpactPoint.clearance must be finite and >= 0, got {self.clearance!r}")
        if not (np.isfinite(float(self.window)) and float(self.window) > 0):
            raise ValueError(f"ImpactPoint.window must be finite and > 0, got {self.window!r}")
        if not 0.0 < float(self.stop_fraction) < 1.0:
            raise ValueError(f"ImpactPoint.stop_fraction must be in (0, 1), got {self.stop_fraction!r}")
        window_substeps = max(1, int(round(float(self.window) / float(mj_model.opt.timestep))))
        return ImpactModel(
            site,
            body,
            normal / norm,
            c_max,
            float(self.dt_impact),
            tau,
            float(self.margin),
            contact,
            self.enforce,
            surface,
            float(self.clearance),
            window_substeps,
            float(self.stop_fraction),
            striking_geoms(mj_model, body),
        )


def striking_geoms(mj_model: mujoco.MjModel, body: int) -> np.ndarray:
    """``(ngeom,)`` bool: the geoms whose contacts are the point's strikes: those of ``body`` and of every body it
    carries (its subtree); where none of them can collide (``contype`` and ``conaffinity`` 0: Gymnasium ``Pusher``'s
    fingertip body ``tips_arm``), those of the nearest body above it whose subtree has one (the pusher's wrist), so
    that a point's strikes are never silently unmeasured."""
    collides = (mj_model.geom_contype != 0) | (mj_model.geom_conaffinity != 0)
    while True:
        in_subtree = np.zeros(mj_model.nbody, bool)
        in_subtree[body] = True
        for b in range(body + 1, mj_model.nbody):  # a body's parent has a smaller index
            in_subtree[b] = in_subtree[mj_model.body_parentid[b]]
        geoms = in_subtree[mj_model.geom_bodyid]
        if np.any(geoms & collides) or body == 0:
            return geoms
        body = int(mj_model.body_parentid[body])


def peak_torque(robot) -> np.ndarray:
    """``(n,)`` each shielded actuator's largest joint torque [N m or N]: ``|gear| max|forcerange|`` where the force
    is limited, else ``|gear gain| max|ctrlrange|`` for a motor (no bias); ``ValueError`` naming the joints where
    neither bounds it (a servo without ``forcerange``: its force grows with the position error)."""
    force = np.max(np.abs(robot.force_range), axis=1)
    motor = np.all(robot.bias == 0, axis=1)
    ctrl = np.where(motor, np.abs(robot.gain) * np.max(np.abs(robot.ctrl_range), axis=1), np.inf)
    peak = np.abs(robot.gear) * np.minimum(force, ctrl)
    unbounded = [robot.names[i] for i in np.flatnonzero(~np.isfinite(peak))]
    if unbounded:
        raise ValueError(
            f"joints {unbounded}: no forcerange bounds their actuators' torque; pass ImpactPoint.tau_imp_max"
        )
    return peak


def pre_impact_velocities(v, lower, upper, dt, a_max, v_max):
    """``(lo, hi)`` ``(..., n)``, not sorted: the joint velocities a strike may meet, ``v + dt [lower - a_max, upper +
    a_max]`` (this step's box and what the next step adds: a strike early in the next step comes at this step's end
    velocity, and the rest of that step adds at most ``dt a_max``) clipped to ``±v_max``: the next step's bounds keep
    the velocity there, and a box reaching past it would read as (17) already violated at ``w = 0`` and cap the speed
    at 0 whenever a joint runs near ``v_max``. Shared by ``ImpactModel.halfspace`` and ``SafetyWrapper.impact_cap``."""
    reach = jnp.broadcast_to(dt * a_max, jnp.shape(v))
    return jnp.maximum(v + dt * lower - reach, -v_max), jnp.minimum(v + dt * upper + reach, v_max)


def remove_excess(a, g, h, u):
    """``a`` ``(..., n)`` with its excess over the row ``g . a <= h`` (``g`` ``(..., n)``, ``h`` ``(..., 1)``) removed
    along ``u`` (where ``g . u > 1e-6``; elsewhere ``a`` as it is): the task-consistent correction before the
    projection, ``u = M^-1 J^T M_eq n̂`` changing only the point's normal acceleration (a projection alone turns the
    excess into tangential motion, docs/impact.md). Shared by ``SafeAcceleration`` and ``SafetyWrapper``."""
    gu = jnp.sum(g * u, axis=-1, keepdims=True)
    excess = jnp.maximum(jnp.sum(g * a, axis=-1, keepdims=True) - h, 0.0)
    ok = gu > 1e-6
    return a - jnp.where(ok, excess / jnp.where(ok, gu, 1.0), 0.0) * u


REACH_STEPS = 3  # control steps of approach at the velocity limits within which a surface makes the cap active


def _digest(x):
    """``ImpactModel.key``'s digest of one field: an array's dtype, shape and bytes (``array_key``), a contact model's
    ``key()``, else ``repr``."""
    if isinstance(x, np.ndarray):
        return array_key(x)
    return x.key() if isinstance(x, _impact.ContactModel) else repr(x)


class ImpactModel(NamedTuple):
    """``ImpactPoint`` resolved against a model: ``site`` (-1: the body's origin), ``body``, the unit ``normal``,
    ``c_max``, ``dt_impact`` [s], ``tau_imp_max`` ``(n,)`` [N m], ``margin``, ``contact``, ``enforce``, ``surface``
    (``(3,)`` or None), ``clearance`` [m], the strike measurement's ``window_substeps`` and ``stop_fraction``, and
    ``strike_geoms`` ``(ngeom,)`` bool (``striking_geoms``)."""

    site: int
    body: int
    normal: np.ndarray
    c_max: float
    dt_impact: float
    tau_imp_max: np.ndarray
    margin: float
    contact: object
    enforce: bool
    surface: object
    clearance: float
    window_substeps: int
    stop_fraction: float
    strike_geoms: np.ndarray

    def point_position(self, d) -> jax.Array:
        """``(3,)`` the point in the world at ``d``'s kinematics (MJX data after ``fwd_position``)."""
        return d.site_xpos[self.site] if self.site >= 0 else d.xpos[self.body]

    def jacobian(self, sys, d, dofs) -> jax.Array:
        """``(3, n)`` the point's translational Jacobian on the shielded dofs (``mjx.jac``), at ``d``'s state."""
        jacp, _ = mjx.jac(sys, d, self.point_position(d), self.body)
        return jnp.swapaxes(jacp[np.asarray(dofs)], 0, 1)

    def jacobian_rate(self, sys, d, dofs) -> jax.Array:
        """``(3, n)`` its time derivative at ``d``'s state and velocity (after ``fwd_velocity``)."""
        jdot, _ = _mjx_support.jac_dot(sys, d, self.point_position(d), self.body)  # not re-exported by mjx 3.17
        return jnp.swapaxes(jdot[np.asarray(dofs)], 0, 1)

    def halfspace(self, M, J, J_rate, point, q, v, limits, dt, lower, upper):
        """``(G (1, n), h (1,), cap, u (n,), active)``: the cap [m/s] at ``(q, v)`` for pre-impact velocities in
        ``v + dt [lower - a_max, upper + a_max]`` within ``±v_max``, and its row ``G a <= h`` on the end-of-step
        speed (module docstring). ``M`` ``(n, n)`` the shielded joints' mass matrix, ``J`` ``(3, n)``, ``J_rate``
        its time derivative: the row reads the end-of-step speed through ``J + dt J_rate`` (the Jacobian where the
        step ends, to first order: with ``J`` alone, the pusher's wrist turning at 2 rad/s moved its measured
        approach speed past a 1.4 mm/s cap by up to 8 mm/s). ``u = M^-1 J^T M_eq n̂`` (``J u = n̂``): the joint
        direction that changes only the point's normal acceleration, along which the decision first removes a
        command's excess (``SafetyWrapper``'s task-consistent correction: a projection alone turns the excess into
        tangential motion, docs/impact.md).

        ``point`` ``(3,)``: the point's position [m]. With a ``surface`` the row is ``active`` only where the gap to the
        plane, ``n̂ . (surface - point) - clearance``, is at most ``REACH_STEPS dt w + w^2 / (2 D)`` with
        ``w = min(S, max(n̂ . J v, 0) + REACH_STEPS dt D)``, ``S = sum_i |n̂ . J_i| v_max_i`` and
        ``D = sum_i |n̂ . J_i| a_max_i`` (the point's fastest approach and hardest braking along ``normal`` at the
        joints' limits, at this pose; ``w`` the fastest approach it can reach from its speed now within
        ``REACH_STEPS`` steps): from farther, it cannot reach the plane within those steps, nor before it has been
        braked toward the cap after them; elsewhere the row is ``0 a <= 1`` (always met).
        ``REACH_STEPS`` covers this step and the next (this step's end speed is the next step's approach) and the
        Jacobian's turn; it is a kinematic estimate at the current pose, not a bound (where the bounds or the torques
        keep some joints from braking, less than ``D`` is available): measured, ``benchmarks/impact_third_party.py``."""
        dtype = jnp.result_type(v)
        dt = jnp.asarray(dt, dtype)
        v_max = jnp.broadcast_to(jnp.asarray(limits.v_max, dtype), v.shape)
        lo, hi = pre_impact_velocities(v, lower, upper, dt, jnp.asarray(limits.a_max, dtype), v_max)
        normal = jnp.asarray(self.normal, dtype)
        cap = _impact.impact_speed_cap(
            M,
            J,
            normal,
            q,
            v,
            limits,
            jnp.asarray(self.tau_imp_max, dtype),
            dt,
            self.c_max,
            self.dt_impact,
            _impact.DEFAULT_REG,
            v_pre_range=(jnp.minimum(lo, hi), jnp.maximum(lo, hi)),
            contact=self.contact,
        ).cap
        cap = cap * jnp.asarray(self.margin, dtype)
        G, h = _impact.speed_cap_halfspace(M, J + dt * J_rate, normal, v, cap, dt)
        u = -_impact.impact_jump(M, J, normal, v, 0.0, 1.0, _impact.DEFAULT_REG).dq_dw
        active = jnp.ones((), bool)
        if self.surface is not None:
            gap = jnp.dot(normal, jnp.asarray(self.surface, dtype) - jnp.asarray(point, dtype)) - self.clearance
            lever = jnp.abs(normal @ J)
            S = jnp.sum(lever * v_max)
            D = jnp.sum(lever * jnp.broadcast_to(jnp.asarray(limits.a_max, dtype), v.shape))
            # the fastest approach the point can have within REACH_STEPS steps from its speed now, then its braking
            w = jnp.minimum(S, jnp.maximum(jnp.dot(normal, J @ v), 0.0) + REACH_STEPS * dt * D)
            reach = REACH_STEPS * dt * w + w * w / (2.0 * jnp.maximum(D, jnp.finfo(dtype).tiny))
            active = gap <= reach
            G = jnp.where(active, G, 0.0)
            h = jnp.where(active, h, 1.0)
        return G, h, cap, u, active

    def c_jacobian(self, model: mujoco.MjModel, data: mujoco.MjData, dofs, rate: bool = False) -> np.ndarray:
        """``(3, n)`` the point's translational Jacobian on the shielded dofs from C MuJoCo (``mj_jac``; its time
        derivative ``mj_jacDot`` with ``rate``), at ``data``'s kinematics (and velocities for the rate)."""
        point = data.site_xpos[self.site] if self.site >= 0 else data.xpos[self.body]
        jac = np.zeros((3, model.nv))
        (mujoco.mj_jacDot if rate else mujoco.mj_jac)(model, data, jac, None, point, self.body)
        return jac[:, dofs]

    def c_terms(self, model: mujoco.MjModel, data: mujoco.MjData, dofs) -> tuple:
        """``(M, J, J_rate, point)`` for ``halfspace`` from C MuJoCo (float64): the shielded joints' block of
        ``mj_fullM`` (``(n, n)``), the two Jacobians and the point, at ``data``'s state (after the position and
        velocity stages)."""
        M = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, M)
        point = data.site_xpos[self.site] if self.site >= 0 else data.xpos[self.body]
        J, J_rate = self.c_jacobian(model, data, dofs), self.c_jacobian(model, data, dofs, True)
        return M[dofs, :][:, dofs], J, J_rate, np.array(point)

    def c_striking(self, data: mujoco.MjData) -> bool:
        """``striking`` from C MuJoCo: a geom of the point's subtree is in one of ``data``'s contacts (within its
        ``includemargin``)."""
        c = data.contact
        mask = self.strike_geoms
        return bool(np.any((c.dist < c.includemargin) & (mask[c.geom1] | mask[c.geom2]))) if data.ncon else False

    def key(self) -> tuple:
        """A hashable digest of every field (a compiled decision's cache key; the contact model's own ``key``)."""
        return tuple(_digest(x) for x in self)

    def striking(self, d) -> jax.Array:
        """``()`` bool: a geom of the point's subtree is in contact in MJX data ``d`` (after collision): a contact
        within its ``includemargin`` (MuJoCo's rule for a contact's constraint rows: ``dist < margin - gap``; Brax's
        ``pusher`` has a 2 mm margin, so its wrist is pushed before it penetrates)."""
        impl = d._impl if hasattr(d, "_impl") else d
        if impl.ncon == 0:
            return jnp.zeros((), bool)
        c = impl.contact
        mask = jnp.asarray(self.strike_geoms)
        return jnp.any((c.dist < c.includemargin) & (mask[c.geom1] | mask[c.geom2]))

    def approach_speed(self, J, v) -> jax.Array:
        """``()`` the point's speed along ``normal`` [m/s] for joint velocity ``v`` (positive: approaching)."""
        return jnp.dot(jnp.asarray(self.normal, J.dtype), J @ v)


__all__ = ["ImpactModel", "ImpactPoint"]
