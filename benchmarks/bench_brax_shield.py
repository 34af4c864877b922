"""Cost of ``JointLimitShield`` on a Brax MJX env: jitted, vmapped step at batch 256, shielded vs unwrapped.

    .venv/bin/python benchmarks/bench_brax_shield.py [--env pusher] [--batch 256] [--steps 50]

Both are timed in the same run (interleaved repeats, median of 5): a ``lax.scan`` of ``--steps``
random-action steps over the batch; the first call of each (its compilation, unless JAX's persistent
cache holds it) is timed too. Prints a table and one JSON line.
"""

import argparse
import json
import time
import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags before jax)

import jax
import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import brax.envs

from jaxlimits.envs import JointLimitShield


def rollout_fn(env, batch, steps):
    @jax.jit
    def run(key):
        st = jax.vmap(env.reset)(jax.random.split(key, batch))

        def body(st, k):
            a = jax.random.uniform(k, (batch, env.action_size), minval=-1.0, maxval=1.0)
            return jax.vmap(env.step)(st, a), None

        st, _ = jax.lax.scan(body, st, jax.random.split(key, steps))
        return st.reward.sum()

    return run


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--env", default="pusher")
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--v_max", type=float, default=2.0)
    p.add_argument("--method", default="viability")
    p.add_argument("--no-torque-limits", action="store_true", help="JointLimitShield(torque_limits=False)")
    args = p.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = brax.envs.get_environment(args.env, backend="mjx")
        shielded = JointLimitShield(
            brax.envs.get_environment(args.env, backend="mjx"),
            v_max=args.v_max,
            method=args.method,
            torque_limits=not args.no_torque_limits,
        )
    fns = {
        "unwrapped": rollout_fn(plain, args.batch, args.steps),
        "shielded": rollout_fn(shielded, args.batch, args.steps),
    }
    first = {}
    for k, f in fns.items():
        t = time.perf_counter()
        jax.block_until_ready(f(jax.random.PRNGKey(0)))  # compile (and one run)
        first[k] = time.perf_counter() - t
    times = {k: [] for k in fns}
    for r in range(5):
        for k, f in fns.items():
            t = time.perf_counter()
            jax.block_until_ready(f(jax.random.PRNGKey(r + 1)))
            times[k].append(time.perf_counter() - t)
    per = {k: float(np.median(v)) / (args.batch * args.steps) * 1e6 for k, v in times.items()}
    print(f"{args.env}, batch {args.batch}, {args.method}, torque limits {not args.no_torque_limits}: us per env-step")
    for k, v in per.items():
        print(f"  {k:10s} {v:8.2f}")
    overhead = per["shielded"] / per["unwrapped"] - 1.0
    print(f"  overhead   {overhead:+.1%}")
    print("first call (compilation of the jitted rollout, and one run) [s]")
    for k, v in first.items():
        print(f"  {k:10s} {v:8.1f}")
    print(
        json.dumps(
            {
                "env": args.env,
                "batch": args.batch,
                "unwrapped_us": per["unwrapped"],
                "shielded_us": per["shielded"],
                "overhead": overhead,
                "unwrapped_first_call_s": first["unwrapped"],
                "shielded_first_call_s": first["shielded"],
            }
        )
    )


if __name__ == "__main__":
    main()
