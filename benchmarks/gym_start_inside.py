"""Gymnasium locomotion envs shielded from their own resets vs from starts inside the joint ranges.

    .venv/bin/python benchmarks/gym_start_inside.py                      # Hopper, Walker2d, Ant; 600 steps each
    .venv/bin/python benchmarks/gym_start_inside.py --envs Ant-v5 --steps 300

Gymnasium's Ant resets its ankles 0.52 rad outside their ranges, Hopper and Walker2d their hips and knees at their
upper limits plus noise: states outside any guarantee. For each env, ``JointLimitShieldWrapper(v_max=3.0)`` with
``start_inside`` False (the env's own resets) and True (``Robot.pose_inside``: the initial pose moved inside the
ranges shrunk by the reset noise), the same actions (the upper bound of the action box every third step, uniform
samples otherwise, seeded), a reset at every termination or truncation. Prints a table of the wrapper's tally (steps
with a position / velocity excess at some substep and the largest, resets that started outside, non-viable steps,
contact-disturbed steps) and, last, ONE JSON line with the same figures.
"""

from __future__ import annotations

import argparse
import json
import warnings

import jaxlimits.envs  # noqa: F401  (XLA CPU flags before JAX starts)

import gymnasium

from jaxlimits.envs.gym_shield import JointLimitShieldWrapper

KEYS = ("position_violations", "velocity_violations", "max_position_excess", "max_velocity_excess", "starts_outside")


def run(env_id: str, start_inside: bool, steps: int, seed: int = 0) -> dict:
    """The tally of ``steps`` shielded steps of ``env_id`` (see the module docstring)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the start-outside warning (counted) and a_max's quantile
        env = JointLimitShieldWrapper(gymnasium.make(env_id), v_max=3.0, start_inside=start_inside)
        env.reset(seed=seed)
        env.action_space.seed(seed)
        for i in range(steps):
            a = env.action_space.sample() if i % 3 else env.action_space.high
            _, _, term, trunc, _ = env.step(a)
            if term or trunc:
                env.reset(seed=seed + i + 1)
    out = {k: env.tally[k] for k in KEYS + ("nonviable", "disturbed", "steps")}
    env.close()
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--envs", default="Hopper-v5,Walker2d-v5,Ant-v5")
    parser.add_argument("--steps", type=int, default=600)
    args = parser.parse_args()
    rows = []
    print(
        f"{'env':12s} {'start_inside':>12s} {'pos (max)':>18s} {'vel (max)':>18s} {'outside starts':>15s} "
        f"{'non-viable':>10s} {'disturbed':>9s}"
    )
    for env_id in args.envs.split(","):
        for inside in (False, True):
            r = dict(run(env_id, inside, args.steps), env=env_id, start_inside=inside)
            rows.append(r)
            pos = f"{r['position_violations']} ({r['max_position_excess']:.3g})"
            vel = f"{r['velocity_violations']} ({r['max_velocity_excess']:.3g})"
            print(
                f"{env_id:12s} {inside!s:>12s} {pos:>18s} {vel:>18s} {r['starts_outside']:>15d} "
                f"{r['nonviable']:>10d} {r['disturbed']:>9d}",
                flush=True,
            )
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
