"""SafetyWrapper: joint-limit shields around an ``ArmReach`` env, and adversarial rollouts.

Each step the wrapper computes acceleration bounds from the true state (``pipeline_state.qpos``,
``qvel``) with the env's control period, integrator (``"semi_implicit"``) and substep count, projects
the commanded acceleration into them, and steps the env with the projected command.

Methods: ``"none"`` (the command as is, ``action * a_max``, even outside ``[-1, 1]``), ``"clip"``
(clipped to ``[-a_max, a_max]``: what a plain RL env does), ``"naive"`` (Del Prete's eq. 2:
end-of-step position and velocity), ``"viability"`` (Alg. 3, exact for the semi-implicit model),
and ``"jerk"`` when ``jaxlimits.acc_bounds`` supports it (checked at construction).

Metrics added to the env's (see ``arm.py`` for ``violation/*``, ``count/*``, ``accel_error``,
``model_error``): ``intervention`` = ``max_j |a_safe - a_des|`` [rad/s^2] and ``viable`` (1.0 when
every joint started the step in the viability kernel). ``info['a_des']``, ``info['a_safe']``,
``info['lower']``, ``info['upper']`` hold the step's command and bounds.

``torque_box=True`` also intersects the bounds with the per-state torque-feasible box
(``jaxlimits.torque.torque_acc_box_conservative`` at the step's start state, MJX ``M`` and ``h``):
``[-s a_max, s a_max]`` with ``s = clip(box_scale, 0, 1)``, inside which every acceleration needs at
most ``torque_box_margin * tau_max``. Where a joint's interval and the box are disjoint the limits
win: the joint keeps the end of its limit interval nearest the box (the least demanding action the
limits allow, the braking side), the motors may then saturate, and the step is counted in
``metrics['torque_box_conflict']`` (``jaxlimits.intersect``, whose conflict rule this is). Metrics ``torque_box_scale``
(the unclipped ``s``) and ``torque_box_conflict`` are added.

``impact=`` (envs with ``impact_terms``, e.g. ``WallStrike``) adds the impact-aware speed cap of
Wang & Kheddar (``jaxlimits.impact``, see ``docs/impact.md``): the largest contact-normal velocity
whose predicted jumps keep the position (16), velocity (17) and impulsive torque (20) bounds, for
every pre-impact velocity the step's box allows *and the next step's* (``v + dt [lower - a_max, upper +
a_max]``: the velocity at the end of this step is the next step's approach speed, and a strike early in
the next step meets it before that step's own cap can slow it down), is imposed on the end-effector velocity
at the end of the step as one halfspace ``J^T n̂ . (v + a dt) <= margin * cap``. The excess is first removed
along ``u = M^-1 J^T M_eq n̂`` (``J u = n̂``: the tangential end-effector acceleration is kept; a
Euclidean projection alone would turn the excess into tangential motion), then the box and the
halfspace go through ``jl.solve_box_qp(..., G=, h=)`` (box exact, halfspace with least violation when the box
cannot meet it: counted in ``metrics['impact_infeasible']``). Metrics ``impact_cap`` [m/s] and
``impact_infeasible`` are added; the measured impact metrics (``impact/*``) are the env's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxlimits as jl
import jaxlimits.impact as _impact
import jaxlimits.torque as _torque
from jaxlimits.envs.arm import ArmReach, State, Wrapper
from jaxlimits.envs.impact_point import pre_impact_velocities, remove_excess

METHODS = ("none", "clip", "naive", "viability", "jerk")
# the derivative a differentiating learner (Brax APG) sees through the shield: the projection's own two
# (``jl.PROJECTION_GRADIENTS``) and "exact_fixed_bounds", the exact projection derivative with the bounds held
# constant (no derivative of the viability bounds with respect to the state): it separates the two paths of
# the exact derivative (docs/training.md, APG against PPO)
SHIELD_GRADIENTS = (*jl.PROJECTION_GRADIENTS, "exact_fixed_bounds")
BOUND_METHODS = ("naive", "viability", "jerk")  # the methods whose bounds a contact must not push the joints out of


def project(a_des, lower, upper, gradient: str = "exact"):
    """The projection of the command into the bounds (the one call to change for another metric).

    ``jl.project_box`` with the Euclidean metric: the clip, exactly inside ``[lower, upper]``;
    ``gradient`` is ``jl.project_box``'s (``"exact"`` or ``"straight_through"``).
    """
    return jl.project_box(a_des, lower, upper, gradient=gradient)


class SafetyWrapper(Wrapper):
    """Shield an ``ArmReach`` env's acceleration commands (must wrap the base env directly).

    Args:
      env: an ``ArmReach``.
      method: one of ``METHODS``.
      dt_factor: compute the bounds for a control period ``dt_factor * env.dt`` (Del Prete Sec. V
        uses 2x to smooth the braking); the env still steps ``env.dt``. 1.0 is exact. The bounds'
        substep length stays the simulator's (``dt_factor * frame_skip`` substeps, which must be an
        integer): stretching the substep instead breaks the guarantee (measured on the Panda,
        Sec. V-B with 2x: 1.7 mrad overshoot at 0.08 rad/s), while a prefix of a viable
        semi-implicit trajectory with the same substep is viable.
      torque_box: also intersect the bounds with the per-state torque-feasible box (see the module
        docstring and ``jaxlimits.intersect``). Costs one more MJX ``(M, h)`` evaluation per step.
        It makes every command realisable at the step's start state; it cannot restore a guarantee
        that ``a_max`` itself breaks: the viability bounds assume that ``|a| <= a_max`` (full
        braking) is available at every later state, which holds for the torque-derived ``a_max``
        (the env's default, up to sampling) and not for a datasheet one (conflicts are counted).
      torque_box_margin: the box uses ``torque_box_margin * tau_max``: room for the change of ``M``
        and ``h`` during the step's substeps (the box is computed at the step's start). Measured on
        the Panda with datasheet ``a_max``: with 1.0, 4 of 12 800 adversarial steps exceeded a torque
        limit (by <= 1.3 N m) without a conflict; with 0.95, none of 25 600.

      gradient: the derivative of the projection seen by anything that differentiates through the
        step (Brax APG): ``"exact"`` (default; the clip's true derivative, so a clipped joint passes
        no gradient to its command) or ``"straight_through"`` (the identity w.r.t. the command, a
        learning heuristic, not the projection's derivative; see ``jl.solve_box_qp``) or
        ``"exact_fixed_bounds"`` (the exact derivative with the bounds held constant: no derivative of the
        bounds w.r.t. the state). The value of the safe command is the same, bit for bit, so the guarantee
        does not depend on it.
      impact: ``None`` (off: behaviour unchanged), ``True`` (the env's ``impact`` spec) or a dict
        overriding any of ``c_range``, ``dt_impact``, ``tau_imp_max`` (n,) [N m], ``margin`` (the
        cap is scaled by it, default 1.0), ``reg``, ``contact`` (a ``jaxlimits.impact.ContactModel``;
        the env's, ``CoulombContact(friction)`` for ``WallStrike``), ``anticipate`` (default ``False``: the cap
        on the end-of-step normal speed; ``True``: on the largest normal speed any joints braking toward rest
        can leave, ``speed_cap_halfspace(..., box=)``, and the cap computed with rest inside each joint's
        pre-impact velocity range) (see ``jaxlimits.impact``). Needs an env with
        ``impact_terms(q, v) -> (M, J, normal)`` and an ``impact`` spec (``WallStrike``).

    Attributes: ``name`` (``method``, ``+torque_box``/``+impact``/``+impact+anticipate`` when on; the key
    ``adversarial_rollout`` reports under).
    """

    def __init__(
        self,
        env: ArmReach,
        method: str = "viability",
        dt_factor: float = 1.0,
        torque_box: bool = False,
        torque_box_margin: float = 0.95,
        impact=None,
        gradient: str = "exact",
    ):
        super().__init__(env)
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if gradient not in SHIELD_GRADIENTS:
            raise ValueError(f"gradient must be one of {SHIELD_GRADIENTS}, got {gradient!r}")
        self.gradient = gradient
        if not isinstance(env, ArmReach):
            raise TypeError(f"SafetyWrapper wraps an ArmReach directly, got {type(env).__name__}")
        # the System this env is shielded with: its own step refuses another (a domain randomisation passing by)
        vars(env).setdefault("_safety_sys", env.sys)
        self.method = method
        self.torque_box = bool(torque_box)
        if not 0.0 < torque_box_margin <= 1.0:
            raise ValueError(f"torque_box_margin must be in (0, 1], got {torque_box_margin}")
        self.torque_box_margin = float(torque_box_margin)
        self.impact = self._impact_options(env, impact)
        impact_name = ("+impact" + ("+anticipate" if self.impact["anticipate"] else "")) if self.impact else ""
        self.name = method + ("+torque_box" if self.torque_box else "") + impact_name
        self.limits = env.limits
        self.dt_factor = float(dt_factor)
        substeps = env.frame_skip * self.dt_factor
        if self.dt_factor < 1.0 or abs(substeps - round(substeps)) > 1e-9:
            raise ValueError(
                f"dt_factor * frame_skip must be an integer >= frame_skip, got {dt_factor} * {env.frame_skip}"
            )
        self.substeps = int(round(substeps))
        self.dt_bounds = env.dt * self.dt_factor
        if method in ("naive", "viability", "jerk"):
            jl.make_discretisation(self.dt_bounds, env.integrator, self.substeps)  # validates eagerly
            if method != "naive":
                jl.check_condition_11(env.limits, self.dt_bounds)

    @staticmethod
    def _impact_options(env, impact):
        if impact is None or impact is False:
            return None
        if not hasattr(env, "impact_terms") or not hasattr(env, "impact"):
            raise ValueError(
                f"impact= needs an env with impact_terms and an impact spec (WallStrike), got {type(env).__name__}"
            )
        opts = {
            "c_range": env.impact.c_range,
            "dt_impact": env.impact.dt_impact,
            "tau_imp_max": np.asarray(env.impact.tau_imp_max, np.float64),
            "margin": 1.0,
            "reg": _impact.DEFAULT_REG,
            "contact": env.impact.contact,
            "anticipate": False,
        }
        if impact is not True:
            unknown = set(impact) - set(opts)
            if unknown:
                raise ValueError(f"impact: unknown options {sorted(unknown)}; known {sorted(opts)}")
            opts.update(impact)
        opts["c_max"] = _impact.check_restitution(*opts["c_range"])
        tau = np.broadcast_to(np.asarray(opts["tau_imp_max"], np.float64), (env.n,)).copy()
        if not np.all(np.isfinite(tau)) or np.any(tau <= 0):
            raise ValueError(f"impact: tau_imp_max must be finite and > 0, got {tau.tolist()}")
        opts["tau_imp_max"] = tau
        _impact.check_contact(opts["contact"])
        if not isinstance(opts["anticipate"], bool):
            raise ValueError(f"impact: anticipate must be True or False, got {opts['anticipate']!r}")
        if not (float(opts["dt_impact"]) > 0 and 0 < float(opts["margin"]) <= 1.0):
            raise ValueError(
                f"impact: need dt_impact > 0 and 0 < margin <= 1, got {opts['dt_impact']}, {opts['margin']}"
            )
        return opts

    def impact_cap(self, state: State, lower, upper):
        """``(G, h, cap, u)``: the speed cap [m/s] at the state, its halfspace in ``a`` (``G`` (..., 1, n))
        and the joint direction ``u = M^-1 J^T M_eq n̂`` (``J u = n̂``) along which ``_shield`` removes excess speed.

        The cap holds for every pre-impact velocity ``v + dt [lower - a_max, upper + a_max]`` within ``±v_max``: this
        step's box and what the next step adds to it (a strike early in the next step comes at this step's end
        velocity, and the rest of that step adds at most ``dt a_max``), clipped to the velocity limits the next
        step's bounds keep. Batched states are flattened and vmapped over.
        """
        o = self.impact
        d = state.pipeline_state
        q, v = d.qpos, d.qvel
        n = self.env.n
        lead = q.shape[:-1]
        dt = jnp.float32(self.env.dt)
        v_max = jnp.broadcast_to(jnp.asarray(self.limits.v_max, jnp.float32), v.shape)
        lo, hi = pre_impact_velocities(v, lower, upper, dt, jnp.asarray(self.limits.a_max, jnp.float32), v_max)
        lo, hi = lo.reshape((-1, n)), hi.reshape((-1, n))
        if o["anticipate"]:  # a joint braked toward rest later approaches at any speed between now and rest
            lo, hi = jnp.minimum(lo, 0.0), jnp.maximum(hi, 0.0)
        qf, vf = q.reshape((-1, n)), v.reshape((-1, n))
        M, J, nrm = jax.vmap(self.env.impact_terms)(qf, vf)
        cap = _impact.impact_speed_cap(
            M,
            J,
            nrm,
            qf,
            vf,
            self.limits,
            o["tau_imp_max"],
            dt,
            o["c_max"],
            o["dt_impact"],
            o["reg"],
            v_pre_range=(jnp.minimum(lo, hi), jnp.maximum(lo, hi)),
            contact=o["contact"],
        ).cap
        cap = cap * jnp.float32(o["margin"])
        box = None
        if o["anticipate"]:  # finite: the accelerations that keep the velocity within v_max (all, for the bounds)
            keep_lo, keep_hi = (-v_max - v) / dt, (v_max - v) / dt
            a_lo = jnp.clip(lower, keep_lo, keep_hi).reshape((-1, n))
            box = (a_lo, jnp.maximum(jnp.clip(upper, keep_lo, keep_hi).reshape((-1, n)), a_lo))
        G, h = _impact.speed_cap_halfspace(M, J, nrm, vf, cap, dt, box=box)
        u = -_impact.impact_jump(M, J, nrm, vf, 0.0, 1.0, o["reg"]).dq_dw  # u = M^-1 J^T M_eq n̂
        return G.reshape(lead + (1, n)), h.reshape(lead + (1,)), cap.reshape(lead), u.reshape(lead + (n,))

    def bounds(self, state: State, a_prev=None):
        """``jl.Bounds`` for the state of ``state`` (``(n,)``, or batched along leading axes).

        With ``torque_box`` these are the limit bounds intersected with the torque box.
        """
        return self._bounds(state, a_prev)[0]

    def torque_acc_box(self, state: State):
        """``(lower, upper, scale)``: the torque-feasible box ``clip(scale, 0, 1) * [-a_max, a_max]`` at the state.

        ``scale`` is ``jaxlimits.torque.box_scale`` for ``torque_box_margin * tau_max`` (shape
        ``(...)``); the box equals ``torque_acc_box_conservative``. Batched states are flattened and
        vmapped over.
        """
        d = state.pipeline_state
        q, v = d.qpos, d.qvel
        n = self.env.n
        lead = q.shape[:-1]
        M, h = jax.vmap(self.env.mass_and_bias)(q.reshape((-1, n)), v.reshape((-1, n)))
        tau = np.asarray(self.env.tau_max, np.float32) * np.float32(self.torque_box_margin)
        a_max = jnp.asarray(self.limits.a_max, jnp.float32)
        box = _torque.TorqueBox(M, h, tau, a_max)
        b = box.bounds(q, v)  # the state is in M and h
        return b.lower.reshape(lead + (n,)), b.upper.reshape(lead + (n,)), box.scale().reshape(lead)

    def _bounds(self, state: State, a_prev=None):
        """``(bounds, extra_metrics)``; the extra metrics are those of the torque box (empty without it)."""
        b = self._limit_bounds(state, a_prev)
        if not self.torque_box:
            return b, {}
        t_lo, t_hi, scale = self.torque_acc_box(state)
        # the limits first: where the box is disjoint from them they win (jl.intersect's rule); viable stays theirs
        both = jl.intersect(b, jl.Bounds(t_lo, t_hi, jnp.ones(t_lo.shape, bool)))
        extra = {"torque_box_scale": scale, "torque_box_conflict": jnp.any(both.conflict, axis=-1).astype(jnp.float32)}
        return both.bounds, extra

    def _limit_bounds(self, state: State, a_prev=None):
        d = state.pipeline_state
        a_max = jnp.asarray(self.limits.a_max, jnp.float32)
        if self.method == "none":
            big = jnp.full_like(d.qpos, jnp.inf)
            return jl.Bounds(-big, big, jnp.ones(d.qpos.shape, bool))
        if self.method == "clip":
            return jl.Bounds(
                jnp.broadcast_to(-a_max, d.qpos.shape),
                jnp.broadcast_to(a_max, d.qpos.shape),
                jnp.ones(d.qpos.shape, bool),
            )
        kwargs = dict(method=self.method, integrator=self.env.integrator, substeps=self.substeps)
        if self.method == "jerk":
            kwargs["a_prev"] = state.info["a_prev"] if a_prev is None else a_prev
        return jl.acc_bounds(d.qpos, d.qvel, self.limits, self.dt_bounds, **kwargs)

    def shield(self, state: State, a_des):
        """``(a_safe, bounds)`` for the command ``a_des`` [rad/s^2]."""
        a_safe, b, _ = self._shield(state, a_des)
        return a_safe, b

    def _shield(self, state: State, a_des):
        """Project ``a_des``; a command with any NaN/inf joint is replaced, whole, by braking.

        Braking is ``-sign(v) a_max`` per joint, projected into the bounds (for ``viability`` the
        hardest deceleration they allow, which keeps the state viable); it is counted in
        ``extra["nonfinite_action"]`` (1.0 for that step). So a non-finite command never reaches
        the simulator, whatever the method (``"none"`` included).
        """
        b, extra = self._bounds(state)
        gradient = self.gradient
        if gradient == "exact_fixed_bounds":
            b, gradient = jax.tree.map(jax.lax.stop_gradient, b), "exact"
        v = state.pipeline_state.qvel
        bad = ~jnp.all(jnp.isfinite(a_des), axis=-1, keepdims=True)
        brake = -jnp.sign(v) * jnp.asarray(self.limits.a_max, jnp.float32)
        a_in = jnp.where(bad, brake, a_des)
        extra = dict(extra, nonfinite_action=bad[..., 0].astype(jnp.float32))
        if not self.impact:
            return project(a_in, b.lower, b.upper, gradient), b, extra
        G, h, cap, u = self.impact_cap(state, b.lower, b.upper)
        # task-consistent correction first: remove the excess approach speed along u = M^-1 J^T M_eq n̂
        # (J u = n̂: only the normal end-effector acceleration changes, not the tangential one), then
        # the exact projection onto {box, halfspace} (a no-op when the corrected command is inside)
        a_task = remove_excess(a_in, G[..., 0, :], h, u)
        res = jl.solve_box_qp(a_task, b.lower, b.upper, G=G, h=h, gradient=gradient)
        extra = dict(extra, impact_cap=cap, impact_infeasible=res.infeasible.astype(jnp.float32))
        return res.x, b, extra

    def step(self, state: State, action) -> State:
        # the decision's torque model in full float32 on a GPU too, as the physics (``arm._mjx_tracing``)
        with jax.default_matmul_precision("highest"):
            a_des = jnp.asarray(action, jnp.float32) * jnp.asarray(self.limits.a_max, jnp.float32)
            a_safe, b, extra = self._shield(state, a_des)
            return self.finish(state, a_des, a_safe, b, extra)

    def band(self, b, a_safe):
        """``(lower, upper)``: the accelerations a contact may leave each substep at (envs with contacts keep
        the realised acceleration inside it where the motors can), the bounds widened to hold ``a_safe``;
        ``None`` for the methods without bounds (``none``, ``clip``)."""
        if self.method not in BOUND_METHODS:
            return None
        return jnp.minimum(b.lower, a_safe), jnp.maximum(b.upper, a_safe)

    def finish(self, state: State, a_des, a_safe, b, extra=None) -> State:
        """Step the env with ``a_safe`` and record the shield's metrics (shared by ``step`` and rollouts)."""
        # the strike record of an env with contacts tells the strikes whose approach the cap could not bound
        cap_unmet = (extra or {}).get("impact_infeasible", jnp.zeros((), jnp.float32)) > 0
        nstate = self.env.step_acc(state, a_safe, self.band(b, a_safe), cap_unmet, capped=bool(self.impact))
        metrics = dict(nstate.metrics)
        # a replaced non-finite command counts in nonfinite_action, not as an (infinite) intervention
        metrics["intervention"] = jnp.max(jnp.where(jnp.isfinite(a_des), jnp.abs(a_safe - a_des), 0.0), axis=-1)
        metrics["viable"] = jnp.all(b.viable, axis=-1).astype(jnp.float32)
        metrics.update(extra or {})
        info = dict(nstate.info)
        info.update(a_des=a_des, a_safe=a_safe, lower=b.lower, upper=b.upper)
        return nstate.replace(metrics=metrics, info=info)

    def reset(self, rng) -> State:
        state = self.env.reset(rng)
        zero = jnp.zeros((), jnp.float32)
        metrics = dict(state.metrics, intervention=zero, viable=jnp.ones((), jnp.float32), nonfinite_action=zero)
        if self.torque_box:
            metrics.update(torque_box_scale=zero, torque_box_conflict=zero)
        if self.impact:
            metrics.update(impact_cap=zero, impact_infeasible=zero)
        n = self.env.n
        info = dict(
            state.info,
            a_des=jnp.zeros((n,), jnp.float32),
            a_safe=jnp.zeros((n,), jnp.float32),
            lower=jnp.zeros((n,), jnp.float32),
            upper=jnp.zeros((n,), jnp.float32),
        )
        return state.replace(metrics=metrics, info=info)


__all__ = ["METHODS", "SafetyWrapper", "project"]
