"""Adversarial rollouts, the measurement behind the shields' claims: ``shield_rollout`` for a
``JointLimitShield``-wrapped Brax env, ``adversarial_rollout`` for the project's ``ArmReach`` envs under
``SafetyWrapper`` (several shields in one compile).

``shield_rollout(env, batch, steps)`` runs ``batch`` envs for ``steps`` control steps in one jitted
scan, the envs split evenly over ``POLICIES`` (normalised actions in ``[-1, 1]``: every target or
torque at its upper bound, at its lower bound, bang-bang with a random period per joint, uniform
random), each restarted every ``episode`` steps, and counts per policy, at every physics substep
(``JointLimitShield``'s metrics): position / velocity / torque violations, saturation, NaN
substitutions, non-viable steps, contact disturbances. A trajectory is *disturbed* from the first
step in which a contact pushed a shielded joint (``shield/disturbance > 0``) until its restart;
violations are also counted for undisturbed trajectories alone (the guarantee's scope).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxlimits as jl
from jaxlimits.envs.arm import VIOLATION_KEYS, ArmReach
from jaxlimits.envs.safety import SafetyWrapper

POLICIES = ("upper", "lower", "bang_bang", "random")
_MAXED = ("position", "velocity", "torque", "accel_error", "beyond_bounds", "contact_corrected")
_COUNTED = (
    "position",
    "velocity",
    "torque",
    "saturated",
    "nonfinite",
    "nonviable",
    "disturbance",
    "torque_conflict",
    "beyond_bounds",
    "contact_corrected",
)


def _action(kind, signs, period, t, key):
    rand = jax.random.uniform(key, signs.shape, jnp.float32, -1.0, 1.0)
    bang = jnp.where((t // period) % 2 == 0, signs, -signs)
    return jnp.select([kind == 0, kind == 1, kind == 2], [jnp.ones_like(signs), -jnp.ones_like(signs), bang], rand)


def inside_reset(env, margin: float = 0.01):
    """``env.reset`` with the shielded joints clipped into their ranges shrunk by ``margin`` [rad or m]: for
    envs whose own reset starts at or past a limit (Brax ``pusher``: elbow and wrist flex at their upper
    limit 0 plus noise), which is outside any guarantee (counted as non-viable otherwise). ``env`` may step a batch
    itself (Brax's ``DomainRandomizationVmapWrapper`` around the shield): the reset then takes ``(batch, 2)`` keys."""
    r = env.robot
    lo = np.where(r.limited, r.limits.q_min + margin, -np.inf).astype(np.float32)
    hi = np.where(r.limited, r.limits.q_max - margin, np.inf).astype(np.float32)
    adr = np.asarray(r.qpos_adr)

    def reset(key):
        st = env.reset(key)
        d = st.pipeline_state
        q = d.qpos.at[..., adr].set(jnp.clip(d.qpos[..., adr], lo, hi))
        return st.replace(pipeline_state=d.replace(qpos=q))

    return reset


def shield_rollout(
    env, batch: int, steps: int, seed: int = 0, episode: int = 200, reset=None, batched: bool = False
) -> dict:
    """Run the adversarial policies through ``env`` (a ``JointLimitShield``); see the module docstring.
    ``batched``: ``env`` resets and steps ``batch`` members itself (Brax's ``DomainRandomizationVmapWrapper``
    around the shield, ``batch`` its members; ``reset`` then takes ``(batch, 2)`` keys), else it is vmapped here.

    Returns a dict: ``env_steps``; per policy ``p`` and in total: ``count/<k>`` (env-steps with
    ``k`` > 0 for ``k`` in position, velocity, torque, saturated, nonfinite, nonviable, disturbance),
    ``max/<k>`` for position, velocity, torque, accel_error, and ``undisturbed/count/position``,
    ``undisturbed/count/velocity``, ``undisturbed/max/accel_error``. With an impact point (``impact=``, enforced
    or measured): ``count/impact_active`` (steps the cap applied: all without ``ImpactPoint.surface``),
    ``count/impact_infeasible``; ``count/over_cap`` (steps no contact disturbed whose approach speed
    exceeds the cap of the step before and its own, ``max(cap_t-1, cap_t)``, by over 1 % + 1 mm/s: the step before's
    cap bounds its end speed, this step's its own; judged only where both steps applied and met their caps and not
    on a restart's step); ``count/strikes`` (steps where a contact disturbance begins) and ``max/strike_speed`` [m/s]
    (the approach speed in such a step), ``count/strike_over_cap`` (those over the cap as above, where judged); the
    point's strikes as the shield measures them (``envs/strike_record.py``): ``count/measured_strikes``,
    ``count/impact`` (those whose impulsive joint torque exceeded ``tau_imp_max``), ``max/strike_ratio``.
    """
    reset = env.reset if reset is None else reset
    n_act = env.action_size
    kind_np = np.arange(batch) % len(POLICIES)

    @jax.jit
    def run(key):
        k_reset, k_sign, k_per, k_roll = jax.random.split(key, 4)
        keys = jax.random.split(k_reset, batch)
        states0 = reset(keys) if batched else jax.vmap(reset)(keys)
        signs = jnp.where(jax.random.bernoulli(k_sign, 0.5, (batch, n_act)), 1.0, -1.0).astype(jnp.float32)
        period = jax.random.randint(k_per, (batch, n_act), 5, 60)
        kind = jnp.asarray(kind_np)[:, None]
        step = env.step if batched else jax.vmap(env.step)
        impact = "shield/impact_speed" in states0.metrics

        def body(carry, t):
            states, disturbed, acc = carry
            restart = (t > 0) & (t % episode == 0)
            states = jax.tree.map(lambda a, b: jnp.where(restart, a, b), states0, states)
            disturbed = jnp.where(restart, False, disturbed)
            a = _action(kind, signs, period, t, jax.random.fold_in(k_roll, t))
            ns = step(states, a)
            m = {k: ns.metrics[f"shield/{k}"] for k in _COUNTED + ("accel_error",)}
            extra = {}
            if impact:
                prev, now = states.metrics, ns.metrics
                speed, cap = now["shield/impact_speed"], now["shield/impact_cap"]
                feasible = (prev["shield/impact_infeasible"] == 0) & (now["shield/impact_infeasible"] == 0)
                feasible &= (prev["shield/impact_active"] > 0) & (now["shield/impact_active"] > 0)
                judged = (t % episode != 0) & feasible
                above = judged & (speed > 1.01 * jnp.maximum(prev["shield/impact_cap"], cap) + 1e-3)
                strike = (m["disturbance"] > 0) & (prev["shield/disturbance"] == 0) & (t % episode != 0)
                extra = {
                    "count/impact_active": acc["count/impact_active"] + (now["shield/impact_active"] > 0),
                    "count/impact_infeasible": acc["count/impact_infeasible"] + (now["shield/impact_infeasible"] > 0),
                    "count/over_cap": acc["count/over_cap"] + (above & (m["disturbance"] == 0)),
                    "count/strikes": acc["count/strikes"] + strike,
                    "count/strike_over_cap": acc["count/strike_over_cap"] + (strike & above),
                    "max/impact_speed": jnp.maximum(acc["max/impact_speed"], speed),
                    "max/strike_speed": jnp.maximum(acc["max/strike_speed"], jnp.where(strike, speed, 0.0)),
                    # the point's strikes as the shield measures them (envs/strike_record.py)
                    "count/measured_strikes": acc["count/measured_strikes"] + (now["shield/strike"] > 0),
                    "count/impact": acc["count/impact"] + (now["shield/impact"] > 0),
                    "max/strike_ratio": jnp.maximum(acc["max/strike_ratio"], now["shield/strike_ratio"]),
                }
            disturbed = disturbed | (m["disturbance"] > 0)
            clean = ~disturbed
            acc = {
                **extra,
                **{f"count/{k}": acc[f"count/{k}"] + (m[k] > 0) for k in _COUNTED},
                **{f"max/{k}": jnp.maximum(acc[f"max/{k}"], m[k]) for k in _MAXED},
                "undisturbed/count/position": acc["undisturbed/count/position"] + (clean & (m["position"] > 0)),
                "undisturbed/count/velocity": acc["undisturbed/count/velocity"] + (clean & (m["velocity"] > 0)),
                "undisturbed/max/accel_error": jnp.maximum(
                    acc["undisturbed/max/accel_error"], jnp.where(clean, m["accel_error"], 0.0)
                ),
            }
            return (ns, disturbed, acc), None

        zi = jnp.zeros((batch,), jnp.int32)
        zf = jnp.zeros((batch,), jnp.float32)
        acc0 = {f"count/{k}": zi for k in _COUNTED}
        acc0.update({f"max/{k}": zf for k in _MAXED})
        acc0.update(
            {"undisturbed/count/position": zi, "undisturbed/count/velocity": zi, "undisturbed/max/accel_error": zf}
        )
        if impact:
            acc0.update({k: zi for k in ("count/impact_infeasible", "count/over_cap", "count/strikes")})
            acc0["count/impact_active"] = zi
            acc0.update({"count/strike_over_cap": zi, "max/impact_speed": zf, "max/strike_speed": zf})
            acc0.update({"count/measured_strikes": zi, "count/impact": zi, "max/strike_ratio": zf})
        (_, _, acc), _ = jax.lax.scan(body, (states0, jnp.zeros((batch,), bool), acc0), jnp.arange(steps))
        return acc

    acc = jax.device_get(run(jax.random.PRNGKey(seed)))
    out = {"env_steps": batch * steps}

    def reduce(sel):
        r = {}
        for k, x in acc.items():
            r[k] = int(x[sel].sum()) if "count" in k else float(x[sel].max())
        return r

    out.update(reduce(np.ones(batch, bool)))
    for j, p in enumerate(POLICIES):
        for k, x in reduce(kind_np == j).items():
            out[f"{p}/{k}"] = x
    return out


# ---- adversarial rollouts of the project's ArmReach envs under SafetyWrapper ---------------------
ARM_POLICIES = ("toward_limits", "bang_bang", "random")
_EXTRA_DEFAULTS = {"torque_box_scale": np.inf, "torque_box_conflict": 0.0}  # for shields without the torque box


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
    (cheap) and the env's own is selected. Envs cycle over the ``ARM_POLICIES`` and restart from their
    initial state every ``episode`` steps (an unshielded arm otherwise spins up without bound).
    ``methods`` holds method names or ``SafetyWrapper`` instances (of ``env``; reported under their
    ``name``, e.g. ``"viability+torque_box"``). ``batch`` is an int (envs per method) or a dict
    name -> envs. Returns a dict per name with ``env_steps``, ``count/*`` (violating env-steps),
    ``max/*`` (largest violation magnitude), ``accel_error`` and ``model_error`` (max),
    ``intervention`` (mean), per policy counts of position violations, and for torque-box shields
    ``count/torque_box_conflict``, ``min/torque_box_scale`` and ``count/torque_unflagged`` (torque
    violations in steps without a conflict: the box was computed at the step's start state).
    """
    wrappers = [m if isinstance(m, SafetyWrapper) else SafetyWrapper(env, m) for m in methods]
    names = [w.name for w in wrappers]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate shield names {names}")
    if any(w.env is not env for w in wrappers):
        raise ValueError("every SafetyWrapper must wrap the env passed")
    n, M = env.n, len(methods)
    sizes = [batch[m] if isinstance(batch, dict) else int(batch) for m in names]
    B = sum(sizes)
    method_id_np = np.repeat(np.arange(M), sizes)
    policy_np = np.concatenate([np.arange(b) % len(ARM_POLICIES) for b in sizes])

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
            cands = [w._shield(state, a_des) for w in wrappers]
            a_safe = jnp.stack([c[0] for c in cands])[mid]
            lower = jnp.stack([c[1].lower for c in cands])[mid]
            upper = jnp.stack([c[1].upper for c in cands])[mid]
            viable = jnp.stack([c[1].viable for c in cands])[mid]
            extra = {
                k: jnp.stack([c[2].get(k, jnp.asarray(d, jnp.float32)) for c in cands])[mid]
                for k, d in _EXTRA_DEFAULTS.items()
            }
            ns = wrappers[0].finish(state, a_des, a_safe, jl.Bounds(lower, upper, viable), extra)
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
                "count/torque_box_conflict": acc["count/torque_box_conflict"] + m["torque_box_conflict"],
                "count/torque_unflagged": acc["count/torque_unflagged"]
                + m["count/torque"] * (1.0 - m["torque_box_conflict"]),
                "min/torque_box_scale": jnp.minimum(acc["min/torque_box_scale"], m["torque_box_scale"]),
            }
            return (ns.replace(metrics=states.metrics), acc), None

        zeros = jnp.zeros((B,), jnp.float32)
        acc0 = {
            **{f"count/{k}": zeros for k in VIOLATION_KEYS},
            **{f"max/{k}": zeros for k in VIOLATION_KEYS},
            "accel_error": zeros,
            "model_error": zeros,
            "intervention": zeros,
            "count/torque_box_conflict": zeros,
            "count/torque_unflagged": zeros,
            "min/torque_box_scale": jnp.full((B,), jnp.inf, jnp.float32),
        }
        states0 = states
        (_, acc), _ = jax.lax.scan(body, (states, acc0), jnp.arange(steps))
        return acc, method_id, policy

    acc, method_id, policy = jax.device_get(run(jax.random.PRNGKey(seed)))
    out = {}
    for i, (m, w) in enumerate(zip(names, wrappers)):
        sel = method_id == i
        r = {"env_steps": int(sel.sum()) * steps}
        for k in VIOLATION_KEYS:
            r[f"count/{k}"] = int(acc[f"count/{k}"][sel].sum())
            r[f"max/{k}"] = float(acc[f"max/{k}"][sel].max())
        r["accel_error"] = float(acc["accel_error"][sel].max())
        r["model_error"] = float(acc["model_error"][sel].max())
        r["intervention"] = float(acc["intervention"][sel].sum()) / r["env_steps"]
        for j, p in enumerate(ARM_POLICIES):
            r[f"count/position/{p}"] = int(acc["count/position"][sel & (policy == j)].sum())
        if w.torque_box:
            r["count/torque_box_conflict"] = int(acc["count/torque_box_conflict"][sel].sum())
            r["count/torque_unflagged"] = int(acc["count/torque_unflagged"][sel].sum())
            r["min/torque_box_scale"] = float(acc["min/torque_box_scale"][sel].min())
        out[m] = r
    return out
