"""Env throughput with and without the viability shield, and Alg. 4 (torque -> acceleration bounds) timing.

    .venv/bin/python benchmarks/bench_env.py            # planar + Panda, batch 1/64/1024 (+ torque box); Alg. 4 N=1e6 Panda
    .venv/bin/python benchmarks/bench_env.py --quick    # planar, batch 64; Alg. 4 N=2e4 planar (< 60 s)

Throughput: one jitted ``lax.scan`` of ``steps`` control steps over a batch of envs with random
actions in [-1, 1], per variant: ``unshielded`` (``ArmReach.step``), ``viability``
(``SafetyWrapper(env, "viability").step``: bounds, projection, the wrapper's metrics and info) and,
in the full run, ``torque_box`` (``SafetyWrapper(env, "viability", torque_box=True).step``: one more
MJX ``(M, h)`` per step). Each variant is compiled once (compile time reported); then ``--repeats``
rounds run every variant once, in an order rotated each round, so that a load change on a shared
machine hits all variants alike. Reported: the median env-steps/s of each variant, and the overhead
as the median over rounds of the per-round time ratio (shielded / unshielded - 1), which cancels
slow drifts in the machine's load, with its interquartile range, for wall-clock time and for the
process's CPU time (``time.process_time``: time the process was descheduled by other jobs does not
count, so it is the steadier figure on a shared machine).

``shield us``: the shield alone (``acc_bounds`` + ``project``, vmapped, in a ``lax.scan`` whose state
depends on the previous output so nothing is hoisted; commands drawn up front) in microseconds per env-step, with
``step us`` the unshielded env-step's time from the same rounds: their ratio is the shield's cost
without the noise of two full-step timings.

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

import jaxlimits as jl
import jaxlimits.torque as torque
from jaxlimits.envs.arm import dynamics_c, make_panda_reach, make_planar_reach, sample_states
from jaxlimits.envs.safety import SafetyWrapper, project

STEPS = {1: 1000, 64: 200, 1024: 20}  # about 20-500 ms per timed call


def _rollout(env_like, batch: int, steps: int, n: int):
    @jax.jit
    def run(key):
        states = jax.vmap(env_like.reset)(jax.random.split(key, batch))

        def body(s, k):
            a = jax.random.uniform(k, (batch, n), jnp.float32, -1.0, 1.0)
            s = jax.vmap(env_like.step)(s, a)
            return s, s.metrics["violation/position"]

        s, viol = jax.lax.scan(body, states, jax.random.split(key, steps))
        return s.pipeline_state.qpos, jnp.max(viol)

    return run


def _shield_only(env, batch: int, steps: int):
    """The viability shield alone on a chain of states (each step's state depends on the last command)."""
    w = SafetyWrapper(env, "viability")
    lim = env.limits
    a_max = jnp.asarray(lim.a_max, jnp.float32)
    dt, sub = w.dt_bounds, w.substeps

    @jax.jit
    def run(key):
        kq, kv, ka = jax.random.split(key, 3)
        q = jax.random.uniform(
            kq, (batch, env.n), jnp.float32, jnp.asarray(lim.q_min, jnp.float32), jnp.asarray(lim.q_max, jnp.float32)
        )
        v = jax.random.uniform(kv, (batch, env.n), jnp.float32, -1.0, 1.0) * jnp.asarray(lim.v_max, jnp.float32)

        a_des = jax.random.uniform(ka, (steps, batch, env.n), jnp.float32, -1.0, 1.0) * a_max  # drawn up front

        def body(c, a_des):
            q, v = c
            b = jax.vmap(
                lambda qq, vv: jl.acc_bounds(
                    qq, vv, lim, dt, method="viability", integrator="semi_implicit", substeps=sub
                )
            )(q, v)
            a = project(a_des, b.lower, b.upper)
            return (q + 1e-9 * a, v + 1e-9 * a), None

        (q, v), _ = jax.lax.scan(body, (q, v), a_des)
        return q

    return run


def throughput(env, batch: int, steps: int, repeats: int, torque_box: bool):
    variants = {"unshielded": env, "viability": SafetyWrapper(env, "viability")}
    if torque_box:
        variants["torque_box"] = SafetyWrapper(env, "viability", torque_box=True)
    fns = {k: _rollout(e, batch, steps, env.n) for k, e in variants.items()}
    fns["shield_only"] = _shield_only(env, batch, steps)
    out = {"steps": steps}
    viol = {}
    for k, f in fns.items():
        t0 = time.perf_counter()
        res = jax.block_until_ready(f(jax.random.PRNGKey(0)))
        out[f"compile_s/{k}"] = time.perf_counter() - t0
        if k != "shield_only":
            viol[k] = float(res[1])
    names = list(fns)
    times = {k: [] for k in names}
    cpu = {k: [] for k in names}
    for r in range(repeats):
        order = names[r % len(names) :] + names[: r % len(names)]
        for k in order:
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(fns[k](jax.random.PRNGKey(r + 1)))
            times[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    for k in names:
        t = np.asarray(times[k])
        if k == "shield_only":
            out["shield_us"] = 1e6 * float(np.median(t)) / (batch * steps)
            continue
        out[k] = batch * steps / float(np.median(t))
        out[f"{k}_best"] = batch * steps / float(np.min(t))
        out[f"{k}_max_violation"] = viol[k]
        if k != "unshielded":
            for tag, tt, base in (("", t, times["unshielded"]), ("_cpu", np.asarray(cpu[k]), cpu["unshielded"])):
                ratio = tt / np.asarray(base)
                out[f"overhead{tag}_pct/{k}"] = 100.0 * (float(np.median(ratio)) - 1.0)
                out[f"overhead{tag}_pct_iqr/{k}"] = [100.0 * (float(x) - 1.0) for x in np.percentile(ratio, [25, 75])]
    out["step_us"] = 1e6 * float(np.median(times["unshielded"])) / (batch * steps)
    out["shield_cost_pct"] = 100.0 * out["shield_us"] / out["step_us"]
    out["compile_s"] = sum(v for k, v in out.items() if k.startswith("compile_s/"))
    return out


def alg4(env, n_samples: int, chunk: int):
    lim = env.limits
    q, v = sample_states(np.random.default_rng(0), lim.q_min, lim.q_max, lim.v_max, n_samples)
    qf, vf = q.astype(np.float32), v.astype(np.float32)
    fn = jax.jit(
        lambda q, v: torque.acc_bounds_from_torque(
            env.mass_and_bias,
            lim.q_min,
            lim.q_max,
            lim.v_max,
            env.tau_max,
            n_samples,
            None,
            a_nominal=env.a_max_nominal,
            states=(q, v),
            chunk=chunk,
        )
    )
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
        "n_samples": n_samples,
        "mjx_s": mjx_s,
        "mjx_compile_s": compile_s,
        "c_loop_s": c_s,
        "speedup_vs_c": c_s / mjx_s,
        "max_rel_diff": float(
            max(np.max(np.abs(b.lower - lo_c) / np.abs(lo_c)), np.max(np.abs(b.upper - hi_c) / np.abs(hi_c)))
        ),
        "lower": np.asarray(b.lower).round(3).tolist(),
        "upper": np.asarray(b.upper).round(3).tolist(),
        "conservative_scale": float(b.scale),
    }


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--quick", action="store_true", help="planar arm only, batch 64, no torque box, Alg. 4 with N=2e4 (< 60 s)"
    )
    p.add_argument("--repeats", type=int, default=None, help="interleaved rounds (default 5 with --quick, else 9)")
    args = p.parse_args()
    repeats = args.repeats or (5 if args.quick else 9)
    t_start = time.perf_counter()
    arms = {"planar": make_planar_reach()}
    if not args.quick:
        arms["panda"] = make_panda_reach()
    batches = (64,) if args.quick else (1, 64, 1024)
    rows = {}
    for arm, env in arms.items():
        for b in batches:
            rows[f"{arm}/{b}"] = throughput(env, b, STEPS[b], repeats, torque_box=not args.quick)
            print(f"  {arm}/{b} done ({time.perf_counter() - t_start:.0f} s)", flush=True)
    a4_env = arms["planar"] if args.quick else arms["panda"]
    a4 = alg4(a4_env, 20_000 if args.quick else 1_000_000, 8192)
    a4["arm"] = "planar" if args.quick else "panda"

    tb = not args.quick
    print(
        "overhead %: median over rounds of the per-round time ratio - 1, [interquartile range]; wall clock and "
        "process CPU time (less sensitive to other processes' load)"
    )
    print(
        f"{'arm/batch':<13}{'unshielded/s':>13}{'viability/s':>12}{'overhead % wall':>22}{'overhead % CPU':>22}"
        + (f"{'torque box/s':>13}{'wall %':>8}{'CPU %':>8}" if tb else "")
        + f"{'shield us':>10}{'step us':>9}{'shield %':>9}{'compile s':>10}{'viol':>6}"
    )

    def cell(r, tag, k):
        lo, hi = r[f"overhead{tag}_pct_iqr/{k}"]
        return f"{r[f'overhead{tag}_pct/{k}']:.1f} [{lo:.1f}, {hi:.1f}]"

    for k, r in rows.items():
        line = (
            f"{k:<13}{r['unshielded']:>13.0f}{r['viability']:>12.0f}{cell(r, '', 'viability'):>22}"
            f"{cell(r, '_cpu', 'viability'):>22}"
        )
        if tb:
            line += (
                f"{r['torque_box']:>13.0f}{r['overhead_pct/torque_box']:>8.1f}{r['overhead_cpu_pct/torque_box']:>8.1f}"
            )
        line += (
            f"{r['shield_us']:>10.3f}{r['step_us']:>9.2f}{r['shield_cost_pct']:>9.1f}{r['compile_s']:>10.1f}"
            f"{r['viability_max_violation']:>6.2g}"
        )
        print(line)
    print(
        f"Alg. 4 ({a4['arm']}, N={a4['n_samples']:.0e}): MJX {a4['mjx_s']:.2f} s (compile {a4['mjx_compile_s']:.1f} s), "
        f"C loop mj_fullM+mj_rne {a4['c_loop_s']:.2f} s, speed-up x{a4['speedup_vs_c']:.1f}, "
        f"max rel diff {a4['max_rel_diff']:.1e}"
    )
    print(f"  bounds lower {a4['lower']} upper {a4['upper']}; conservative box scale {a4['conservative_scale']:.3f}")
    wall = time.perf_counter() - t_start
    print(f"wall {wall:.1f} s ({repeats} interleaved rounds)")
    result = {
        "benchmark": "bench_env",
        "quick": args.quick,
        "repeats": repeats,
        "throughput": rows,
        "alg4": a4,
        "device": jax.devices()[0].platform,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "jax_version": jax.__version__,
        "wall_s": wall,
    }
    print("JSON " + json.dumps(result))


if __name__ == "__main__":
    main()
