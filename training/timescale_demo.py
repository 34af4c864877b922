"""Suleiman et al. Scenarios 1 and 2 on a 4-DoF planar arm (notebook 05, tests, ``python -m``).

A planar chain (``planar_fk``/``planar_jac``, pure JAX) follows a quadratic Bézier path of its end
effector. The time-scaled IK (``timescale_ik``) walks the path point by point, closed loop
(``dr = p_{k+1} - fk(q_k)``), each step taking the ``T`` the limits allow; conventional IK
(``fixed_time_ik``) follows the path turned into a trajectory with a uniform time law
(``s = t / t_f``, period ``T_s``), and ``shortest_fixed_tf`` finds the shortest ``t_f`` for which
it never leaves the joint velocity limits (a grid of ``t_f``, every candidate in one batch).

``python -m jaxlimits.training.timescale_demo [--quick]`` prints the table and one JSON line.
"""

from __future__ import annotations

import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits import fixed_time_ik, timescale_ik

LENGTHS = (0.5, 0.4, 0.3, 0.2)  # link lengths [m]
Q0 = (0.2, 0.5, 0.6, 0.5)  # initial joint positions [rad]
V_MAX = 0.5  # joint velocity limit [rad/s] (both scenarios, as in the paper)
R_DOT_MAX = 0.7  # end-effector velocity limit per component [m/s] (Scenario 2)
T_S = 5e-3  # control period of the conventional IK [s] (the paper's)


def planar_fk(q, lengths=LENGTHS):
    """End-effector position ``(..., 2)`` [m] of a planar chain with joint angles ``q (..., n)``."""
    ang = jnp.cumsum(q, axis=-1)
    L = jnp.asarray(lengths, q.dtype)
    return jnp.stack([jnp.sum(L * jnp.cos(ang), -1), jnp.sum(L * jnp.sin(ang), -1)], -1)


def planar_jac(q, lengths=LENGTHS):
    """Jacobian ``(2, n)`` of ``planar_fk`` at one ``q (n,)``."""
    return jax.jacfwd(lambda x: planar_fk(x, lengths))(q)


def bezier_points(s, q0=Q0, lengths=LENGTHS):
    """Quadratic Bézier ``(1-s)^2 P0 + 2 s (1-s) P1 + s^2 P2`` at ``s (k,)``; ``P0 = fk(q0)``."""
    P0 = planar_fk(jnp.asarray(q0, s.dtype), lengths)
    P1 = P0 + jnp.asarray([-0.9, 0.5], s.dtype)
    P2 = P0 + jnp.asarray([-1.0, -0.5], s.dtype)
    s = s[:, None]
    return (1 - s) ** 2 * P0 + 2 * s * (1 - s) * P1 + s**2 * P2


def track_timescale(n_points=2000, r_dot_max=None, alpha=1.0, t_min=1e-4, dtype=jnp.float64):
    """Follow the path through ``n_points`` points with time-scaled IK; a dict of per-step arrays.

    Keys: ``t`` (time at each reached point), ``T``, ``qd`` (joint velocity ``dq/T``), ``ee_vel``
    (``(fk(q_{k+1}) - fk(q_k)) / T``, the realised average), ``ee_cmd`` (``dr / T``, the velocity the
    QP bounds), ``error`` (``||fk(q_{k+1}) - p_{k+1}||``), ``reached``, ``q``.
    """
    pts = bezier_points(jnp.linspace(0.0, 1.0, n_points + 1, dtype=dtype))
    q0 = jnp.asarray(Q0, dtype)

    def step(q, p):
        x = planar_fk(q)
        r = timescale_ik(planar_jac(q), p - x, V_MAX, t_min=t_min, alpha=alpha, r_dot_max=r_dot_max)
        q1 = q + r.dq
        x1 = planar_fk(q1)
        out = dict(
            T=r.t,
            qd=r.dq / r.t,
            ee_vel=(x1 - x) / r.t,
            ee_cmd=(p - x) / r.t,
            error=jnp.linalg.norm(x1 - p),
            reached=r.reached,
            q=q1,
        )
        return q1, out

    _, out = jax.jit(lambda q: jax.lax.scan(step, q, pts[1:]))(q0)
    out["t"] = jnp.cumsum(out["T"])
    return {k: np.asarray(v) for k, v in out.items()}


def track_fixed(t_f, t_s=T_S, n_max=None, dtype=jnp.float64):
    """Conventional IK along ``s = min(k t_s / t_f, 1)`` for a batch of ``t_f (B,)``; per-step arrays ``(steps, B)``.

    ``n_max`` steps are run for every candidate (the longest ``t_f`` decides); steps after a
    candidate's ``t_f`` are masked (``active`` False).
    """
    t_f = jnp.asarray(t_f, dtype)
    if n_max is None:
        n_max = int(np.ceil(float(np.max(np.asarray(t_f))) / t_s)) + 1
    B = t_f.shape[0]
    q0 = jnp.broadcast_to(jnp.asarray(Q0, dtype), (B, 4))

    def step(q, k):
        s = jnp.minimum((k + 1) * t_s / t_f, 1.0)
        p = jax.vmap(lambda si: bezier_points(si[None])[0])(s)
        x = planar_fk(q)
        J = jax.vmap(planar_jac)(q)
        r = fixed_time_ik(J, p - x, t_s, V_MAX)
        q1 = q + r.dq
        active = k * t_s < t_f - 0.5 * t_s
        out = dict(
            qd=r.dq / t_s,
            error=jnp.linalg.norm(planar_fk(q1) - p, axis=-1),
            active=active,
            ee_vel=(planar_fk(q1) - x) / t_s,
        )
        return q1, out

    _, out = jax.jit(lambda q: jax.lax.scan(step, q, jnp.arange(n_max, dtype=dtype)))(q0)
    return {k: np.asarray(v) for k, v in out.items()}


def shortest_fixed_tf(grid, t_s=T_S, rel_tol=1e-9):
    """The shortest ``t_f`` of ``grid`` for which conventional IK stays inside the velocity limits.

    Returns ``(t_f or nan, per-candidate max |qd| / v_max)``.
    """
    out = track_fixed(np.asarray(grid), t_s)
    ratio = np.max(np.where(out["active"][..., None], np.abs(out["qd"]), 0.0), axis=(0, 2)) / V_MAX
    ok = ratio <= 1.0 + rel_tol
    return (float(np.asarray(grid)[np.argmax(ok)]) if np.any(ok) else float("nan")), ratio


def scenarios(quick=False):
    """Both scenarios and the conventional baseline: a dict of figures (float64)."""
    with jax.enable_x64(True):
        n_points = 400 if quick else 2000
        res = {}
        for name, cap in (("scenario1", None), ("scenario2", R_DOT_MAX)):
            t0 = time.perf_counter()
            o = track_timescale(n_points, r_dot_max=cap)
            res[name] = dict(
                total_time=float(o["t"][-1]),
                max_error=float(np.max(o["error"])),
                max_joint_speed=float(np.max(np.abs(o["qd"]))),
                max_ee_speed_component=float(np.max(np.abs(o["ee_vel"]))),
                max_ee_cmd_component=float(np.max(np.abs(o["ee_cmd"]))),
                all_reached=bool(np.all(o["reached"])),
                points=n_points,
                seconds=time.perf_counter() - t0,
            )
        t0 = time.perf_counter()
        grid = np.round(np.arange(1.5, 8.0 + 1e-9, 0.1 if quick else 0.01), 4)
        tf, ratio = shortest_fixed_tf(grid)
        res["conventional"] = dict(
            shortest_tf=tf,
            grid_step=float(grid[1] - grid[0]),
            max_speed_ratio_at_scenario1_time=float(ratio[np.argmin(np.abs(grid - res["scenario1"]["total_time"]))]),
            seconds=time.perf_counter() - t0,
        )
        if np.isfinite(tf):
            o = track_fixed(np.asarray([tf]))
            res["conventional"]["max_error_at_shortest"] = float(np.max(np.where(o["active"], o["error"], 0.0)))
    return res


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    res = scenarios(quick="--quick" in argv)
    print(f"{'case':<34}{'total time [s]':>16}{'max error [m]':>16}{'max |qd| [rad/s]':>18}{'max |ee v_i| [m/s]':>20}")
    for name in ("scenario1", "scenario2"):
        r = res[name]
        print(
            f"{'time-scaled IK, ' + name:<34}{r['total_time']:>16.3f}{r['max_error']:>16.2e}"
            f"{r['max_joint_speed']:>18.6f}{r['max_ee_speed_component']:>20.4f}"
        )
    c = res["conventional"]
    print(
        f"{'conventional IK, shortest fixed t_f':<34}{c['shortest_tf']:>16.3f}{c.get('max_error_at_shortest', float('nan')):>16.2e}"
    )
    print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
