"""Adversarial campaign of ``JointLimitShield`` on third-party Brax envs and the shipped servo arms.

For each env (Brax ``pusher`` and ``reacher`` on MJX, the shipped position-servo Panda and UR5e
``Reach``; Brax ``hopper``, ``walker2d``, ``ant``, ``inverted_pendulum`` at ``v_max`` 3 rad/s) and shield (viability, jerk where the MJCF has j_max, and ``none`` = unshielded through
the same code), ``shield_rollout`` runs the adversarial policies (targets/torques at the upper
bounds, lower bounds, bang-bang, random) and counts violations at every physics substep. Prints a
table and one JSON line.

    .venv/bin/python benchmarks/shield_adversarial.py [--batch 512] [--steps 200] [--env "servo Panda" ...]
"""

import argparse
import json
import time
import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags before jax)

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import brax.envs

from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.adversarial import inside_reset, shield_rollout
from jaxlimits.envs.reach import make_servo_panda_reach, make_ur5e_reach

ENVS = {
    "brax pusher": (lambda: brax.envs.get_environment("pusher", backend="mjx"), dict(v_max=2.0)),
    "brax reacher": (lambda: brax.envs.get_environment("reacher", backend="mjx"), dict(v_max=4.0)),
    "servo Panda": (make_servo_panda_reach, {}),
    "UR5e": (make_ur5e_reach, {}),
    # more of Brax's own envs (MJX, Euler): a planar or free base, feet on the floor; a cart under an unactuated pole
    **{
        f"brax {e}": (lambda e=e: brax.envs.get_environment(e, backend="mjx"), dict(v_max=3.0))
        for e in ("hopper", "walker2d", "ant", "inverted_pendulum")
    },
}
SHIELDS = {
    "brax pusher": ("viability", "none"),
    "brax reacher": ("viability", "none"),
    **{f"brax {e}": ("viability", "none") for e in ("hopper", "walker2d", "ant", "inverted_pendulum")},
    "servo Panda": ("viability", "jerk", "none"),
    "UR5e": ("viability", "none"),
}


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--env", action="append", choices=list(ENVS), help="only these envs (repeatable; default all)")
    args = p.parse_args()
    rows = []
    for name, (make, kw) in ENVS.items():
        if args.env and name not in args.env:
            continue
        for method in SHIELDS[name]:
            env = JointLimitShield(make(), method=method, **kw)
            t = time.time()
            r = shield_rollout(env, args.batch, args.steps, reset=inside_reset(env))
            r.update(env=name, method=method, wall_s=round(time.time() - t, 1))
            rows.append(r)
            print(
                f"{name:13s} {method:9s} steps {r['env_steps']:7d}  pos {r['count/position']:6d} (max {r['max/position']:.2e})"
                f"  vel {r['count/velocity']:6d} (max {r['max/velocity']:.2e})  sat {r['count/saturated']:6d}"
                f"  conflict {r['count/torque_conflict']:5d}  beyond {r['count/beyond_bounds']:5d}"
                f" (max {r['max/beyond_bounds']:.2e})  nonviable {r['count/nonviable']:5d}"
                f"  corrected {r['count/contact_corrected']:5d} (max {r['max/contact_corrected']:.2e})"
                f"  disturbed {r['count/disturbance']:6d}  undisturbed pos/vel {r['undisturbed/count/position']}/"
                f"{r['undisturbed/count/velocity']}  accel err (undisturbed) {r['undisturbed/max/accel_error']:.2e}"
                f"  {r['wall_s']} s",
                flush=True,
            )
    keep = ("env", "method", "env_steps", "wall_s")
    print(
        json.dumps(
            [
                {
                    k: v
                    for k, v in r.items()
                    if k in keep
                    or "/" not in k
                    or k.count("/") <= 2
                    and not k.startswith(("upper", "lower", "bang", "random"))
                }
                for r in rows
            ]
        )
    )


if __name__ == "__main__":
    main()
