"""Env throughput with and without the viability shield, and Alg. 4 (torque -> acceleration bounds) timing.

    .venv/bin/python benchmarks/bench_env.py            # planar + Panda, batch 1/64/1024; Alg. 4 N=1e6 Panda
    .venv/bin/python benchmarks/bench_env.py --quick    # planar, batch 64; Alg. 4 N=2e4 planar (< 60 s on an idle machine)

Throughput: one jitted ``lax.scan`` of ``steps`` control steps over a batch of ``ArmReach`` envs,
random actions in [-1, 1]. Shielded and unshielded runs share one compiled function per batch size:
``lax.cond`` on a scalar flag (outside the vmap, so only the taken branch runs) either projects the
command into the viability bounds (``SafetyWrapper(method="viability").shield``) or passes it
through. Times exclude compilation (reported separately) and are the best of ``--repeats``.

Alg. 4: ``jaxlimits.torque.acc_bounds_from_torque`` over MJX ``(M, h)`` vs the same reduction over
MuJoCo's C ``mj_fullM`` + ``mj_rne`` looped in Python over the same samples, in the same run.

Prints a table and a final ``JSON {...}`` line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jaxlimits.envs  # noqa: F401  (XLA CPU flags before JAX starts)

import jax
import jax.numpy as jnp
import numpy as np

from jaxlimits._src import torque
from jaxlimits.envs.arm import dynamics_c, make_panda_reach, make_planar_reach, sample_states
from jaxlimits.envs.safety import SafetyWrapper


def throughput(env, batch: int, steps: int, repeats: int):
    shield = SafetyWrapper(env, "viability")
    a_max = jnp.asarray(env.limits.a_max, jnp.float32)

    @jax.jit
    def run(key, shielded):
        states = jax.vmap(env.reset)(jax.random.split(key, batch))

        def body(s, k):
            a_des = jax.random.uniform(k, (batch, env.n), jnp.float32, -1.0, 1.0) * a_max[None]
            a = jax.lax.cond(shielded, lambda: jax.vmap(lambda st, ad: shield.shield(st, ad)[0])(s, a_des), lambda: a_des)
            s = jax.vmap(env.step_acc)(s, a)
            return s, s.metrics["violation/position"]

        s, viol = jax.lax.scan(body, states, jax.random.split(key, steps))
        return s.pipeline_state.qpos, jnp.max(viol)

    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    jax.block_until_ready(run(key, True))
    compile_s = time.perf_counter() - t0
    out = {"compile_s": compile_s}
    for name, flag in (("unshielded", False), ("shielded", True)):
        best = np.inf
        for r in range(repeats):
            t0 = time.perf_counter()
            _, viol = jax.block_until_ready(run(jax.random.PRNGKey(r + 1), flag))
            best = min(best, time.perf_counter() - t0)
        out[name] = batch * steps / best
        out[f"{name}_max_violation"] = float(viol)
    out["overhead_pct"] = 100.0 * (out["unshielded"] / out["shielded"] - 1.0)
    return out


def alg4(env, n_samples: int, chunk: int):
    lim = env.limits
    q, v = sample_states(np.random.default_rng(0), lim.q_min, lim.q_max, lim.v_max, n_samples)
    qf, vf = q.astype(np.float32), v.astype(np.float32)
    fn = jax.jit(lambda q, v: torque.acc_bounds_from_torque(env.mass_and_bias, lim.q_min, lim.q_max, lim.v_max,
                                                            env.tau_max, n_samples, None,
                                                            a_nominal=env.a_max_nominal, states=(q, v), chunk=chunk))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(qf, vf))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    b = jax.block_until_ready(fn(qf, vf))
    mjx_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    M, h = dynamics_c(env.mj_model, q, v)
    lo, hi = torque.torque_acc_box(M, h, env.tau_max)
    lo_c, hi_c = np.asarray(lo).max(0), np.asarray(hi).min(0)
    c_s = time.perf_counter() - t0
    return {
        "n_samples": n_samples, "mjx_s": mjx_s, "mjx_compile_s": compile_s, "c_loop_s": c_s,
        "speedup_vs_c": c_s / mjx_s,
        "max_rel_diff": float(max(np.max(np.abs(b.lower - lo_c) / np.abs(lo_c)), np.max(np.abs(b.upper - hi_c) / np.abs(hi_c)))),
        "lower": np.asarray(b.lower).round(3).tolist(), "upper": np.asarray(b.upper).round(3).tolist(),
        "conservative_scale": float(b.scale),
    }


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="planar arm only, batch 64, Alg. 4 with N=2e4 (< 60 s)")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    t_start = time.perf_counter()
    arms = {"planar": make_planar_reach()}
    if not args.quick:
        arms["panda"] = make_panda_reach()
    batches = (64,) if args.quick else (1, 64, 1024)
    steps = {1: 100, 64: 100, 1024: 20}
    rows = {}
    for arm, env in arms.items():
        for b in batches:
            rows[f"{arm}/{b}"] = throughput(env, b, steps[b], args.repeats)
    a4_env = arms["planar"] if args.quick else arms["panda"]
    a4 = alg4(a4_env, 20_000 if args.quick else 1_000_000, 8192)
    a4["arm"] = "planar" if args.quick else "panda"

    print(f"{'arm/batch':<14}{'unshielded/s':>14}{'shielded/s':>14}{'overhead %':>12}{'compile s':>11}{'viol(sh)':>10}")
    for k, r in rows.items():
        print(f"{k:<14}{r['unshielded']:>14.0f}{r['shielded']:>14.0f}{r['overhead_pct']:>12.1f}{r['compile_s']:>11.1f}"
              f"{r['shielded_max_violation']:>10.2g}")
    print(f"Alg. 4 ({a4['arm']}, N={a4['n_samples']:.0e}): MJX {a4['mjx_s']:.2f} s (compile {a4['mjx_compile_s']:.1f} s), "
          f"C loop mj_fullM+mj_rne {a4['c_loop_s']:.2f} s, speed-up x{a4['speedup_vs_c']:.1f}, "
          f"max rel diff {a4['max_rel_diff']:.1e}")
    print(f"  bounds lower {a4['lower']} upper {a4['upper']}; conservative box scale {a4['conservative_scale']:.3f}")
    result = {
        "benchmark": "bench_env", "quick": args.quick, "throughput": rows, "alg4": a4,
        "device": jax.devices()[0].platform, "cpu_count": os.cpu_count(), "machine": platform.machine(),
        "jax_version": jax.__version__, "wall_s": time.perf_counter() - t_start,
    }
    print("JSON " + json.dumps(result))


if __name__ == "__main__":
    main()
