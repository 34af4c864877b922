"""The impact cap with and without a surface, on an arm that can brake: the shipped position-servo Panda's hand
(site ``ee``) over its floor (the plane z = 0).

``ImpactPoint("ee", normal=(0, 0, -1))`` caps the hand's downward speed everywhere; with ``surface=(0, 0, 0)`` only
where the hand could reach the floor before being braked toward the cap (``ImpactModel.halfspace``: the gap at most
``REACH_STEPS dt S + S^2 / (2 D)``). The servo Panda's torque-derived ``a_max`` makes that braking distance short,
so the cap should apply in a fraction of the steps and leave the arm free elsewhere, still never exceeded where it
applied and was met. Under ``shield_rollout``'s adversarial policies (the same starts and actions for both):
the steps the cap applied, the steps it could not be met, steps over it (``shield_rollout``'s ``over_cap``), and the
position / velocity-violating steps. Prints a table and one JSON line (a reference, ``everywhere``, in the same run).

    .venv/bin/python benchmarks/impact_surface.py [--batch 64] [--steps 200]
"""

import argparse
import json
import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags before jax)

from jaxlimits.envs import ImpactPoint, JointLimitShield
from jaxlimits.envs.adversarial import inside_reset, shield_rollout
from jaxlimits.envs.reach import make_servo_panda_reach

SHIELDS = {
    "everywhere": {},
    "near the floor": dict(surface=(0.0, 0.0, 0.0), clearance=0.05),  # the hand's geometry below its ee site
}
KEYS = ("impact_active", "impact_infeasible", "over_cap", "position", "velocity")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--steps", type=int, default=200)
    args = ap.parse_args()
    rows = {}
    for name, options in SHIELDS.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            env = JointLimitShield(make_servo_panda_reach(), impact=ImpactPoint("ee", normal=(0, 0, -1), **options))
        rows[name] = shield_rollout(env, args.batch, args.steps, reset=inside_reset(env))
    total = args.batch * args.steps
    print(f"servo Panda, hand over the floor: {args.batch} envs x {args.steps} steps per shield ({total} env-steps)")
    print(f"{'cap applies':<16}" + "".join(f"{k:>19}" for k in KEYS))
    for name, r in rows.items():
        print(f"{name:<16}" + "".join(f"{r[f'count/{k}']:>19,}" for k in KEYS))
    ref = rows["everywhere"]["count/impact_infeasible"]
    figures = {name: {k: r[f"count/{k}"] for k in KEYS} | {"env_steps": r["env_steps"]} for name, r in rows.items()}
    print(json.dumps({"benchmark": "impact_surface", "infeasible_everywhere": ref, "rows": figures}))
    return figures


if __name__ == "__main__":
    main()
