"""Throughput of the jerk-aware bounds (joint-bounds per second), float32, jitted, large batch.

Measures in one run: ``viability`` (Del Prete, no jerk; the reference), ``jerk`` (zoh and
semi-implicit with 5 substeps), ``is_viable_jerk`` and ``jerk_paper`` (the paper's brute-force grid
of 49,000 (n7, n9) pairs per joint, on a smaller batch). Prints a table and one final line
``JSON {...}`` with the figures and the ratios to ``viability``.

    .venv/bin/python benchmarks/bench_jerk.py           # full (about a minute)
    .venv/bin/python benchmarks/bench_jerk.py --quick   # < 30 s
"""

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlimits as jl  # noqa: E402

LIM = jl.JointLimits(-2.0, 2.0, 2.0, 12.0, j_max=200.0)
DT = 0.01


def states(batch, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.uniform(-2.0, 2.0, batch).astype(np.float32)
    v = rng.uniform(-2.0, 2.0, batch).astype(np.float32)
    a = rng.uniform(-12.0, 12.0, batch).astype(np.float32)
    return jnp.asarray(q), jnp.asarray(v), jnp.asarray(a)


def timeit(fn, args, reps):
    out = fn(*args)
    jax.block_until_ready(out)
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    batch = 2**16 if args.quick else 2**20
    paper_batch = 2**9 if args.quick else 2**12
    reps = 2 if args.quick else 5
    q, v, a = states(batch)
    cases = {
        "viability": (lambda q, v, a: jl.acc_bounds(q, v, LIM, DT, method="viability"), batch),
        "jerk_zoh": (lambda q, v, a: jl.acc_bounds(q, v, LIM, DT, method="jerk", a_prev=a), batch),
        "jerk_semi5": (
            lambda q, v, a: jl.acc_bounds(
                q, v, LIM, DT, method="jerk", integrator="semi_implicit", substeps=5, a_prev=a
            ),
            batch,
        ),
        "is_viable_jerk": (lambda q, v, a: jl.is_viable_jerk(q, v, a, LIM, DT), batch),
        "jerk_paper": (lambda q, v, a: jl.acc_bounds(q, v, LIM, DT, method="jerk_paper", a_prev=a), paper_batch),
    }
    results = {}
    print(f"{'method':<16}{'batch':>10}{'seconds':>12}{'Mjoint-bounds/s':>18}")
    for name, (fn, n) in cases.items():
        sec = timeit(jax.jit(fn), (q[:n], v[:n], a[:n]), reps)
        rate = n / sec
        results[name] = {"batch": n, "seconds": sec, "joint_bounds_per_s": rate}
        print(f"{name:<16}{n:>10}{sec:>12.4f}{rate / 1e6:>18.3f}")
    ref = results["viability"]["joint_bounds_per_s"]
    summary = {
        "dtype": "float32",
        "device": jax.devices()[0].device_kind,
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "quick": args.quick,
        **{f"{k}_per_s": r["joint_bounds_per_s"] for k, r in results.items()},
        **{f"{k}_vs_viability": r["joint_bounds_per_s"] / ref for k, r in results.items() if k != "viability"},
        "jerk_vs_paper": results["jerk_zoh"]["joint_bounds_per_s"] / results["jerk_paper"]["joint_bounds_per_s"],
    }
    print("JSON " + json.dumps(summary))


if __name__ == "__main__":
    main()
