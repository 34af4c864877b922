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
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxlimits as jl
from jaxlimits._src import bounds as _bounds
from jaxlimits.envs.arm import VIOLATION_KEYS, ArmReach, State, Wrapper

METHODS = ("none", "clip", "naive", "viability", "jerk")


def project(a_des, lower, upper):
    """The projection of the command into the bounds (the one call to change for another metric).

    ``jl.project_box`` with the Euclidean metric: the clip, exactly inside ``[lower, upper]``.
    """
    return jl.project_box(a_des, lower, upper)


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
    """

    def __init__(self, env: ArmReach, method: str = "viability", dt_factor: float = 1.0):
        super().__init__(env)
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if method == "jerk" and "jerk" not in _bounds.METHODS:
            raise ValueError("method='jerk' needs jaxlimits.acc_bounds(method='jerk'), which this version lacks")
        if not isinstance(env, ArmReach):
            raise TypeError(f"SafetyWrapper wraps an ArmReach directly, got {type(env).__name__}")
        self.method = method
        self.limits = env.limits
        self.dt_factor = float(dt_factor)
        substeps = env.frame_skip * self.dt_factor
        if self.dt_factor < 1.0 or abs(substeps - round(substeps)) > 1e-9:
            raise ValueError(f"dt_factor * frame_skip must be an integer >= frame_skip, got {dt_factor} * {env.frame_skip}")
        self.substeps = int(round(substeps))
        self.dt_bounds = env.dt * self.dt_factor
        if method in ("naive", "viability", "jerk"):
            _bounds.make_model(self.dt_bounds, env.integrator, self.substeps)  # validates eagerly
            if method != "naive":
                _bounds.check_condition_11(env.limits, self.dt_bounds)

    def bounds(self, state: State, a_prev=None):
        """``jl.Bounds`` for the state of ``state`` (``(n,)``, or batched along leading axes)."""
        d = state.pipeline_state
        a_max = jnp.asarray(self.limits.a_max, jnp.float32)
        if self.method == "none":
            big = jnp.full_like(d.qpos, jnp.inf)
            return jl.Bounds(-big, big, jnp.ones(d.qpos.shape, bool))
        if self.method == "clip":
            return jl.Bounds(jnp.broadcast_to(-a_max, d.qpos.shape), jnp.broadcast_to(a_max, d.qpos.shape),
                             jnp.ones(d.qpos.shape, bool))
        kwargs = dict(method=self.method, integrator=self.env.integrator, substeps=self.substeps)
        if self.method == "jerk":
            kwargs["a_prev"] = state.info["a_prev"] if a_prev is None else a_prev
        return jl.acc_bounds(d.qpos, d.qvel, self.limits, self.dt_bounds, **kwargs)

    def shield(self, state: State, a_des):
        """``(a_safe, bounds)`` for the command ``a_des`` [rad/s^2]."""
        b = self.bounds(state)
        return project(a_des, b.lower, b.upper), b

    def step(self, state: State, action) -> State:
        a_des = jnp.asarray(action, jnp.float32) * jnp.asarray(self.limits.a_max, jnp.float32)
        a_safe, b = self.shield(state, a_des)
        return self.finish(state, a_des, a_safe, b)

    def finish(self, state: State, a_des, a_safe, b) -> State:
        """Step the env with ``a_safe`` and record the shield's metrics (shared by ``step`` and rollouts)."""
        nstate = self.env.step_acc(state, a_safe)
        metrics = dict(nstate.metrics)
        metrics["intervention"] = jnp.max(jnp.abs(a_safe - a_des), axis=-1)
        metrics["viable"] = jnp.all(b.viable, axis=-1).astype(jnp.float32)
        info = dict(nstate.info)
        info.update(a_des=a_des, a_safe=a_safe, lower=b.lower, upper=b.upper)
        return nstate.replace(metrics=metrics, info=info)

    def reset(self, rng) -> State:
        state = self.env.reset(rng)
        zero = jnp.zeros((), jnp.float32)
        metrics = dict(state.metrics, intervention=zero, viable=jnp.ones((), jnp.float32))
        n = self.env.n
        info = dict(state.info, a_des=jnp.zeros((n,), jnp.float32), a_safe=jnp.zeros((n,), jnp.float32),
                    lower=jnp.zeros((n,), jnp.float32), upper=jnp.zeros((n,), jnp.float32))
        return state.replace(metrics=metrics, info=info)


# ---- adversarial rollouts ---------------------------------------------------------------------
POLICIES = ("toward_limits", "bang_bang", "random")


def _policy_action(kind, signs, period, t, key, n):
    """Adversarial commands in normalised units: full acceleration toward a limit per joint
    (random signs), bang-bang with a random period per joint, or uniform in [-1.5, 1.5]."""
    toward = signs
    bang = jnp.where((t // period) % 2 == 0, signs, -signs)
    rand = jax.random.uniform(key, (n,), jnp.float32, -1.5, 1.5)
    return jnp.where(kind == 0, toward, jnp.where(kind == 1, bang, rand))


def adversarial_rollout(env: ArmReach, methods, batch, steps: int, seed: int = 0, episode: int = 100):
    """Run every shield in ``methods`` on ``batch`` envs for ``steps`` control steps, in one jit.

    The physics is compiled once: each env carries a method id, every shield's bounds are computed
    (cheap) and the env's own is selected. Envs cycle over the ``POLICIES`` and restart from their
    initial state every ``episode`` steps (an unshielded arm otherwise spins up without bound).
    ``batch`` is an int (envs per method) or a dict method -> envs. Returns a dict per
    method with ``env_steps``, ``count/*`` (violating env-steps), ``max/*`` (largest violation
    magnitude), ``accel_error`` and ``model_error`` (max), ``intervention`` (mean), and per policy
    counts of position violations.
    """
    wrappers = [SafetyWrapper(env, m) for m in methods]
    n, M = env.n, len(methods)
    sizes = [batch[m] if isinstance(batch, dict) else int(batch) for m in methods]
    B = sum(sizes)
    method_id_np = np.repeat(np.arange(M), sizes)
    policy_np = np.concatenate([np.arange(b) % len(POLICIES) for b in sizes])

    @jax.jit
    def run(key):
        k_reset, k_sign, k_per, k_roll = jax.random.split(key, 4)
        states = jax.vmap(env.reset)(jax.random.split(k_reset, B))
        method_id = jnp.asarray(method_id_np)
        policy = jnp.asarray(policy_np)
        signs = jnp.where(jax.random.bernoulli(k_sign, 0.5, (B, n)), 1.0, -1.0).astype(jnp.float32)
        period = jax.random.randint(k_per, (B, n), 5, 60)
        a_max = jnp.asarray(env.limits.a_max, jnp.float32)

        def one(state, mid, kind, sg, per, t, k):
            a_des = _policy_action(kind, sg, per, t, k, n) * a_max
            cands = [w.shield(state, a_des) for w in wrappers]
            a_safe = jnp.stack([c[0] for c in cands])[mid]
            lower = jnp.stack([c[1].lower for c in cands])[mid]
            upper = jnp.stack([c[1].upper for c in cands])[mid]
            viable = jnp.stack([c[1].viable for c in cands])[mid]
            ns = wrappers[0].finish(state, a_des, a_safe, jl.Bounds(lower, upper, viable))
            return ns.replace(info=state.info | {"a_prev": ns.info["a_prev"], "target": ns.info["target"]})

        def body(carry, t):
            states, acc = carry
            restart = (t > 0) & (t % episode == 0)
            states = jax.tree.map(lambda a, b: jnp.where(restart, a, b), states0, states)
            keys = jax.random.split(jax.random.fold_in(k_roll, t), B)
            ns = jax.vmap(one, in_axes=(0, 0, 0, 0, 0, None, 0))(states, method_id, policy, signs, period, t, keys)
            m = ns.metrics
            acc = {
                **{f"count/{k}": acc[f"count/{k}"] + m[f"count/{k}"] for k in VIOLATION_KEYS},
                **{f"max/{k}": jnp.maximum(acc[f"max/{k}"], m[f"violation/{k}"]) for k in VIOLATION_KEYS},
                "accel_error": jnp.maximum(acc["accel_error"], m["accel_error"]),
                "model_error": jnp.maximum(acc["model_error"], m["model_error"]),
                "intervention": acc["intervention"] + m["intervention"],
            }
            return (ns.replace(metrics=states.metrics), acc), None

        zeros = jnp.zeros((B,), jnp.float32)
        acc0 = {**{f"count/{k}": zeros for k in VIOLATION_KEYS}, **{f"max/{k}": zeros for k in VIOLATION_KEYS},
                "accel_error": zeros, "model_error": zeros, "intervention": zeros}
        states0 = states
        (_, acc), _ = jax.lax.scan(body, (states, acc0), jnp.arange(steps))
        return acc, method_id, policy

    acc, method_id, policy = jax.device_get(run(jax.random.PRNGKey(seed)))
    out = {}
    for i, m in enumerate(methods):
        sel = method_id == i
        r = {"env_steps": int(sel.sum()) * steps}
        for k in VIOLATION_KEYS:
            r[f"count/{k}"] = int(acc[f"count/{k}"][sel].sum())
            r[f"max/{k}"] = float(acc[f"max/{k}"][sel].max())
        r["accel_error"] = float(acc["accel_error"][sel].max())
        r["model_error"] = float(acc["model_error"][sel].max())
        r["intervention"] = float(acc["intervention"][sel].sum()) / r["env_steps"]
        for j, p in enumerate(POLICIES):
            r[f"count/position/{p}"] = int(acc["count/position"][sel & (policy == j)].sum())
        out[m] = r
    return out


__all__ = ["METHODS", "POLICIES", "SafetyWrapper", "adversarial_rollout", "project"]
