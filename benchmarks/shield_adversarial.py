"""Adversarial campaign of ``JointLimitShield`` on third-party Brax envs and the shipped servo arms.

For each env (Brax ``pusher`` and ``reacher`` on MJX, the shipped position-servo Panda, UR5e and Kinova Gen3
``Reach``; Brax ``hopper``, ``walker2d``, ``ant``, ``inverted_pendulum`` at ``v_max`` 3 rad/s) and shield (viability, jerk where the MJCF has j_max, and ``none`` = unshielded through
the same code), ``shield_rollout`` runs the adversarial policies (targets/torques at the upper
bounds, lower bounds, bang-bang, random) and counts violations at every physics substep. Prints a
table and one JSON line.

    .venv/bin/python benchmarks/shield_adversarial.py [--batch 512] [--steps 200] [--env "servo Panda" ...]
        [--randomise 0.5] [--torque_margin 0.25]

``--randomise s``: a domain randomisation, as Brax's trainers apply one (``DomainRandomizationVmapWrapper``
around the shield): every member's masses, joint damping and actuator gains scaled by factors drawn uniformly
in ``[1 - s, 1 + s]`` (independently per body, dof and actuator; a servo's kp and kv with its gain). The robot's
``a_max`` is derived from the nominal model: give it the weakest member's share with ``--torque_margin``
(``0.8 (1 - s) / (1 + s)`` covers the weakest gain against the heaviest masses).
"""

import argparse
import json
import time
import warnings

import jaxlimits.envs  # noqa: F401  (XLA flags before jax)

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    import brax.envs

import jax
import jax.numpy as jnp

from brax.envs.wrappers.training import DomainRandomizationVmapWrapper

from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.adversarial import inside_reset, shield_rollout
from jaxlimits.envs.reach import make_gen3_reach, make_servo_panda_reach, make_ur5e_reach

ENVS = {
    "brax pusher": (lambda: brax.envs.get_environment("pusher", backend="mjx"), dict(v_max=2.0)),
    "brax reacher": (lambda: brax.envs.get_environment("reacher", backend="mjx"), dict(v_max=4.0)),
    "servo Panda": (make_servo_panda_reach, {}),
    "UR5e": (make_ur5e_reach, {}),
    "Gen3": (make_gen3_reach, {}),  # Kinova: four unlimited joints, light wrists under stiff servos
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
    "Gen3": ("viability", "none"),
}


def randomisation(batch: int, spread: float, seed: int = 0):
    """A ``randomization_fn`` (Brax's form, ``sys -> (sys_v, in_axes)``) scaling each of ``batch`` members' body
    masses and inertias, joint damping and actuator gains (a servo's bias with its gain) by ``U[1 - s, 1 + s]``."""

    def fn(sys):
        k = jax.random.split(jax.random.PRNGKey(seed), 3)

        def scale(key, shape):
            return jax.random.uniform(key, (batch, *shape), minval=1.0 - spread, maxval=1.0 + spread)

        m = scale(k[0], sys.body_mass.shape)
        g = scale(k[2], (sys.nu,))
        changed = {
            "body_mass": sys.body_mass * m,
            "body_inertia": sys.body_inertia * m[..., None],
            "dof_damping": sys.dof_damping * scale(k[1], sys.dof_damping.shape),
            "actuator_gainprm": jnp.broadcast_to(sys.actuator_gainprm, (batch, *sys.actuator_gainprm.shape))
            .at[..., 0]
            .multiply(g),
            "actuator_biasprm": jnp.broadcast_to(sys.actuator_biasprm, (batch, *sys.actuator_biasprm.shape))
            .at[..., 1:3]
            .multiply(g[..., None]),
        }
        axes = jax.tree_util.tree_map(lambda _: None, sys).tree_replace({name: 0 for name in changed})
        return sys.tree_replace(changed), axes

    return fn


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--env", action="append", choices=list(ENVS), help="only these envs (repeatable; default all)")
    p.add_argument("--randomise", type=float, default=0.0, help="domain randomisation spread s (module docstring)")
    p.add_argument(
        "--torque_margin",
        type=float,
        default=None,
        help="Robot.from_model's torque_margin (default 0.8): a_max's share",
    )
    args = p.parse_args()
    if not 0.0 <= args.randomise < 1.0:
        p.error(f"--randomise must be in [0, 1), got {args.randomise}")
    rows = []
    for name, (make, kw) in ENVS.items():
        if args.env and name not in args.env:
            continue
        for method in SHIELDS[name]:
            margin = {} if args.torque_margin is None else dict(torque_margin=args.torque_margin)
            try:
                env = JointLimitShield(make(), method=method, **kw, **margin)
            except ValueError as e:  # e.g. jerk bounds that cannot recover at a lowered a_max: refused, eagerly
                print(f"{name:13s} {method:9s} refused: {str(e)[:160]}", flush=True)
                continue
            if args.randomise:
                env = DomainRandomizationVmapWrapper(env, randomisation(args.batch, args.randomise))
            t = time.time()
            r = shield_rollout(env, args.batch, args.steps, reset=inside_reset(env), batched=bool(args.randomise))
            r.update(env=name, method=method, randomise=args.randomise, wall_s=round(time.time() - t, 1))
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
    keep = ("env", "method", "randomise", "env_steps", "wall_s")
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
