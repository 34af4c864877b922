"""Del Prete 2018, Sec. V-B on the Panda: a task-space controller drives the elbow toward its limit.

    .venv/bin/python -m jaxlimits.envs.paper_vb

The end-effector target is the forward kinematics of a configuration whose elbow (joint 4) lies
0.3 rad beyond its lower limit; a lower-priority posture task pulls toward that configuration.
Acceleration-level task-space control (eq. 34, position part):

    a_des = J^+ (kp (x_d - x) - kd J v - Jdot v) + (I - J^+ J) (kp (q_r - q) - kd v),

kp = 10, kd = 2 sqrt(kp) (the paper's gains), ``J^+`` damped least squares. The command is projected
into the acceleration bounds (``naive`` or ``viability``, computed with 2x the control period as in
the paper, and with ``dt_factor = 1``) and realised in MJX by inverse dynamics (``ArmReach``); the
torque limits enter through the torque-derived ``a_max`` (Alg. 4, conservative box). Both methods
run side by side in one compiled scan. Prints, per method, the elbow's closest approach to (or
overshoot of) its lower limit and its speed there, and a ``JSON`` line.
"""

from __future__ import annotations

import json

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from jaxlimits.envs import mjx_stages
from mujoco.mjx._src import support as _support  # jac_dot: MJX 3.17 has no public name for it

import jaxlimits as jl
from jaxlimits.envs.arm import _mjx_tracing, make_panda_reach
from jaxlimits.envs.safety import SafetyWrapper

ELBOW = 3  # joint4


def run(steps: int = 300, kp: float = 10.0, dt_factors=(1.0, 2.0)):
    env = make_panda_reach(torque_samples=20000)
    mjm = env.mj_model
    q0 = np.array(mjm.key_qpos[0])
    q_ref = q0.copy()
    q_ref[ELBOW] = env.limits.q_min[ELBOW] - 0.3
    d = mujoco.MjData(mjm)
    d.qpos[:] = q_ref
    mujoco.mj_kinematics(mjm, d)
    x_d = jnp.asarray(d.site_xpos[env.ee_site], jnp.float32)
    body = int(mjm.site_bodyid[env.ee_site])
    kd = 2.0 * np.sqrt(kp)
    cases = [(m, f) for f in dt_factors for m in ("naive", "viability")]
    shields = [SafetyWrapper(env, m, dt_factor=f) for m, f in cases]
    qr = jnp.asarray(q_ref, jnp.float32)

    @_mjx_tracing
    def controller(dd):
        dd = mjx_stages.fwd_velocity(env.sys, mjx_stages.fwd_position(env.sys, dd))
        x = dd.site_xpos[env.ee_site]
        jacp, _ = mjx.jac(env.sys, dd, x, body)
        jdp, _ = _support.jac_dot(env.sys, dd, x, body)  # not re-exported by mjx 3.17
        J, Jd = jacp.T, jdp.T
        v = dd.qvel
        xdd = kp * (x_d - x) - kd * (J @ v) - Jd @ v
        Jp = J.T @ jnp.linalg.inv(J @ J.T + 1e-4 * jnp.eye(3))
        post = kp * (qr - dd.qpos) - kd * v
        return Jp @ xdd + (jnp.eye(env.n) - Jp @ J) @ post

    @jax.jit
    def roll():
        s0 = env.reset_to(jnp.asarray(q0, jnp.float32), jnp.zeros(env.n, jnp.float32), x_d)
        states = jax.tree.map(lambda x: jnp.stack([x] * len(cases)), s0)

        def one(state, i):
            a_des = controller(state.pipeline_state)
            outs = [w.shield(state, a_des) for w in shields]
            a = jnp.stack([o[0] for o in outs])[i]
            b = jl.Bounds(*(jnp.stack([getattr(o[1], f) for o in outs])[i] for f in ("lower", "upper", "viable")))
            ns = shields[0].finish(state, a_des, a, b)
            return ns.replace(metrics=state.metrics, info=state.info | {"a_prev": ns.info["a_prev"]})

        def body_fn(s, _):
            s = jax.vmap(one)(s, jnp.arange(len(cases)))
            return s, (
                s.pipeline_state.qpos[:, ELBOW],
                s.pipeline_state.qvel[:, ELBOW],
                jnp.linalg.norm(s.pipeline_state.site_xpos[:, env.ee_site] - x_d[None], axis=-1),
            )

        _, traj = jax.lax.scan(body_fn, states, None, length=steps)
        return traj

    q4, v4, err = (np.asarray(x) for x in roll())
    q_min = float(env.limits.q_min[ELBOW])
    out = {}
    for i, (m, f) in enumerate(cases):
        k = int(np.argmin(q4[:, i]))
        crossed = np.flatnonzero(q4[:, i] < q_min)
        out[f"{m}/dt_x{f:g}"] = {
            "min_q_minus_limit": float(q4[k, i] - q_min),
            "speed_at_min": float(abs(v4[k, i])),
            "time_at_min_s": (k + 1) * env.dt,
            "speed_when_crossing": float(abs(v4[crossed[0], i])) if crossed.size else 0.0,
            "steps_past_limit": int(crossed.size),
            "final_ee_error_m": float(err[-1, i]),
        }
    return env, out


def main():
    env, out = run()
    print(
        f"Panda elbow (joint4) toward its lower limit {env.limits.q_min[ELBOW]:.4f} rad, dt = {env.dt} s, "
        f"a_max(joint4) = {env.limits.a_max[ELBOW]:.3f} rad/s^2 (torque-derived)"
    )
    print(
        f"{'bounds':<18}{'min q - q_min':>15}{'|v| there':>11}{'t [s]':>7}{'|v| crossing':>14}{'steps past':>12}{'ee err m':>10}"
    )
    for k, r in out.items():
        print(
            f"{k:<18}{r['min_q_minus_limit']:>15.4g}{r['speed_at_min']:>11.3g}{r['time_at_min_s']:>7.2f}"
            f"{r['speed_when_crossing']:>14.3g}{r['steps_past_limit']:>12d}{r['final_ee_error_m']:>10.3f}"
        )
    print("JSON " + json.dumps(out))


if __name__ == "__main__":
    main()
