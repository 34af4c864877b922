"""Adversarial rollouts of a ``JointLimitShield``-wrapped Brax env: the measurement behind its claims.

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

POLICIES = ("upper", "lower", "bang_bang", "random")
_COUNTED = ("position", "velocity", "torque", "saturated", "nonfinite", "nonviable", "disturbance")


def _action(kind, signs, period, t, key):
    rand = jax.random.uniform(key, signs.shape, jnp.float32, -1.0, 1.0)
    bang = jnp.where((t // period) % 2 == 0, signs, -signs)
    return jnp.select([kind == 0, kind == 1, kind == 2], [jnp.ones_like(signs), -jnp.ones_like(signs), bang], rand)


def inside_reset(env, margin: float = 0.01):
    """``env.reset`` with the shielded joints clipped into their ranges shrunk by ``margin`` [rad or m]: for
    envs whose own reset starts at or past a limit (Brax ``pusher``: elbow and wrist flex at their upper
    limit 0 plus noise), which is outside any guarantee (counted as non-viable otherwise)."""
    r = env.robot
    lo = np.where(r.limited, r.limits.q_min + margin, -np.inf).astype(np.float32)
    hi = np.where(r.limited, r.limits.q_max - margin, np.inf).astype(np.float32)
    adr = np.asarray(r.qpos_adr)

    def reset(key):
        st = env.reset(key)
        d = st.pipeline_state
        return st.replace(pipeline_state=d.replace(qpos=d.qpos.at[adr].set(jnp.clip(d.qpos[adr], lo, hi))))

    return reset


def shield_rollout(env, batch: int, steps: int, seed: int = 0, episode: int = 200, reset=None) -> dict:
    """Run the adversarial policies through ``env`` (a ``JointLimitShield``); see the module docstring.

    Returns a dict: ``env_steps``; per policy ``p`` and in total: ``count/<k>`` (env-steps with
    ``k`` > 0 for ``k`` in position, velocity, torque, saturated, nonfinite, nonviable, disturbance),
    ``max/<k>`` for position, velocity, torque, accel_error, and ``undisturbed/count/position``,
    ``undisturbed/count/velocity``, ``undisturbed/max/accel_error``.
    """
    reset = env.reset if reset is None else reset
    n_act = env.action_size
    kind_np = np.arange(batch) % len(POLICIES)

    @jax.jit
    def run(key):
        k_reset, k_sign, k_per, k_roll = jax.random.split(key, 4)
        keys = jax.random.split(k_reset, batch)
        states0 = jax.vmap(reset)(keys)
        signs = jnp.where(jax.random.bernoulli(k_sign, 0.5, (batch, n_act)), 1.0, -1.0).astype(jnp.float32)
        period = jax.random.randint(k_per, (batch, n_act), 5, 60)
        kind = jnp.asarray(kind_np)[:, None]
        step = jax.vmap(env.step)

        def body(carry, t):
            states, disturbed, acc = carry
            restart = (t > 0) & (t % episode == 0)
            states = jax.tree.map(lambda a, b: jnp.where(restart, a, b), states0, states)
            disturbed = jnp.where(restart, False, disturbed)
            a = _action(kind, signs, period, t, jax.random.fold_in(k_roll, t))
            ns = step(states, a)
            m = {k: ns.metrics[f"shield/{k}"] for k in _COUNTED + ("accel_error",)}
            disturbed = disturbed | (m["disturbance"] > 0)
            clean = ~disturbed
            acc = {
                **{f"count/{k}": acc[f"count/{k}"] + (m[k] > 0) for k in _COUNTED},
                **{
                    f"max/{k}": jnp.maximum(acc[f"max/{k}"], m[k])
                    for k in ("position", "velocity", "torque", "accel_error")
                },
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
        acc0.update({f"max/{k}": zf for k in ("position", "velocity", "torque", "accel_error")})
        acc0.update(
            {"undisturbed/count/position": zi, "undisturbed/count/velocity": zi, "undisturbed/max/accel_error": zf}
        )
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
