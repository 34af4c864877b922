"""The project's planar arm under its two shields, same run: ``SafetyWrapper`` over ``ArmReach`` and the one shield,
``JointLimitShield`` over ``Reach(action="acceleration")`` (``envs/acceleration_actions.py``, docs/shield.md).

    .venv/bin/python benchmarks/one_shield_planar.py [--batch 1024] [--steps 50] [--repeats 5]

Variants, each a jitted ``lax.scan`` of ``--steps`` steps of random actions in ``[-1, 1]`` (joint accelerations
``action * a_max``) over ``--batch`` vmapped envs, timed interleaved (median of ``--repeats``):
``arm`` (``ArmReach``, unshielded), ``arm+SafetyWrapper`` (viability), ``reach`` (``Reach(action="acceleration")``,
unshielded: the ``ctrl`` asking for the acceleration, held over the substeps), ``reach+one shield`` (viability,
``torque_limits=False``: the decision ``SafetyWrapper`` makes) and ``reach+one shield, torque-aware`` (the default:
the torque-space decision). The first call of each (trace and compile) is timed too. Prints a table and, last, ONE
JSON line with the microseconds per env-step and the ratios to ``arm+SafetyWrapper`` measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags before jax)

import jax
import numpy as np

from bench_brax_shield import rollout_fn  # the same timed rollout (this folder is on sys.path: a script)
from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.arm import make_planar_reach
from jaxlimits.envs.reach import make_planar_robot_reach
from jaxlimits.envs.safety import SafetyWrapper


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    arm = make_planar_reach()
    a_max = arm.limits.a_max
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        envs = {
            "arm": arm,
            "arm+SafetyWrapper": SafetyWrapper(make_planar_reach(), "viability"),
            "reach": make_planar_robot_reach(acceleration_scale=a_max),
            "reach+one shield": JointLimitShield(
                make_planar_robot_reach(acceleration_scale=a_max), a_max=a_max, torque_limits=False
            ),
            "reach+one shield, torque-aware": JointLimitShield(
                make_planar_robot_reach(acceleration_scale=a_max), a_max=a_max
            ),
        }
    fns = {k: rollout_fn(e, args.batch, args.steps) for k, e in envs.items()}
    first = {}
    for k, f in fns.items():
        t = time.perf_counter()
        jax.block_until_ready(f(jax.random.PRNGKey(0)))
        first[k] = time.perf_counter() - t
    times = {k: [] for k in fns}
    for r in range(args.repeats):
        order = list(fns) if r % 2 == 0 else list(fns)[::-1]
        for k in order:
            t = time.perf_counter()
            jax.block_until_ready(fns[k](jax.random.PRNGKey(r + 1)))
            times[k].append(time.perf_counter() - t)
    per = {k: float(np.median(v)) / (args.batch * args.steps) * 1e6 for k, v in times.items()}
    ref = per["arm+SafetyWrapper"]
    print(f"planar arm, batch {args.batch}, {args.steps} steps, median of {args.repeats}: us per env-step")
    print(f"{'variant':32s} {'us/step':>9s} {'/ SafetyWrapper':>16s} {'first call s':>13s}")
    for k in fns:
        print(f"{k:32s} {per[k]:9.3f} {per[k] / ref:16.2f} {first[k]:13.1f}")
    out = {"batch": args.batch, "steps": args.steps, "us_per_env_step": per, "first_call_s": first}
    out["ratio_to_safety_wrapper"] = {k: per[k] / ref for k in per}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
