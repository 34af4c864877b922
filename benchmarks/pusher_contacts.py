"""Where the shielded Gymnasium ``Pusher-v5``'s violations come from: its arm's contacts, classified.

    .venv/bin/python benchmarks/pusher_contacts.py                 # 3 000 env-steps per policy class
    .venv/bin/python benchmarks/pusher_contacts.py --steps 600

The campaign's Gymnasium target (``training.campaign_gym``: ``JointLimitShieldWrapper(v_max=2.0)``, method
``"viability"``, under the NaN guard) runs the campaign's policy classes with the campaign's episode keys. Every
step whose substeps went past a position or velocity limit (``info["violation"]``) is classified by the contacts of
the shielded joints' bodies (``Robot`` kinematic trees; Pusher-v5: the wrist's three capsules) at the step's end:
``onset`` (a contact that was not there at the step's start), ``in_contact`` (one that was), ``after_contact`` (none
now, one earlier in the episode), ``no_contact``. For every contact onset the approach speed of the arm's contact
point along the contact normal at the step's start is recorded [m/s] (``J_point v . n``, positive toward the other
geom; the Jacobian at the step's end, where the contact is, the velocity at the step's start): a hard strike is
fast, a touch slow. Also counted: violating steps with a saturated actuator.

Prints a table and, last, ONE JSON line ``{"classes": {...}, "total": {...}}``.
"""

from __future__ import annotations

import argparse
import json

import jaxlimits.envs  # noqa: F401  (XLA CPU flags before JAX starts)

import jax.numpy as jnp
import mujoco
import numpy as np

from jaxlimits.training.campaign_gym import GYM_TARGETS, jitted_policy, episode_keys, to_action_box

CLASSES = ("toward_limit", "bang_bang", "random", "random_walk", "nan_burst")
KINDS = ("onset", "in_contact", "after_contact", "no_contact")


def arm_contacts(m, d, arm_bodies: set, qvel) -> dict:
    """``{(geom1, geom2): approach speed [m/s]}`` of ``d``'s contacts touching ``arm_bodies``: the velocity ``qvel``
    ``(nv,)`` gives the arm's contact point along the normal toward the other geom."""
    out = {}
    jacp = np.zeros((3, m.nv))
    for i in range(d.ncon):
        c = d.contact[i]
        b1, b2 = m.geom_bodyid[c.geom1], m.geom_bodyid[c.geom2]
        if b1 not in arm_bodies and b2 not in arm_bodies:
            continue
        arm_is_1 = b1 in arm_bodies
        normal = c.frame[:3] if arm_is_1 else -c.frame[:3]  # MuJoCo's normal points from geom1 to geom2
        mujoco.mj_jac(m, d, jacp, None, c.pos, b1 if arm_is_1 else b2)
        out[(int(c.geom1), int(c.geom2))] = float(normal @ (jacp @ qvel))
    return out


def run_class(env, cls: str, steps: int) -> dict:
    shield = env.env  # the JointLimitShieldWrapper under the NaN guard
    base = env.unwrapped
    m, d = base.model, base.data
    trees = {int(m.body_rootid[m.jnt_bodyid[j]]) for j in shield.robot.joint_ids}
    arm_bodies = {b for b in range(m.nbody) if int(m.body_rootid[b]) in trees}
    low, high = env.action_space.low.astype(float), env.action_space.high.astype(float)
    policy, classes = jitted_policy(low.shape[0], 200)
    params = {"kind": jnp.asarray(classes.index(cls), jnp.int32)}
    counts = dict.fromkeys(KINDS + ("violating", "saturated"), 0)
    speeds = []
    done = episode = 0
    while done < steps:
        reset_seed, key = episode_keys(0, episode, 1024)
        obs, _ = env.reset(seed=reset_seed)
        episode += 1
        touched = False
        before = set()
        for t in range(min(200, steps - done)):
            v_start = d.qvel.copy()
            action = to_action_box(policy(params, obs, key, np.int32(t)), low, high)
            obs, _, terminated, truncated, info = env.step(action)
            done += 1
            after = arm_contacts(m, d, arm_bodies, v_start)
            new = [pair for pair in after if pair not in before]
            speeds += [after[pair] for pair in new]
            v = info["violation"]
            if v["position"] > 0.0 or v["velocity"] > 0.0:
                counts["violating"] += 1
                counts["saturated"] += bool(info["shield"]["saturated"])
                kind = "onset" if new else "in_contact" if after else "after_contact" if touched else "no_contact"
                counts[kind] += 1
            touched = touched or bool(after)
            before = set(after)
            if terminated or truncated:
                break
    s = np.asarray(speeds)
    counts["onsets"] = int(s.size)
    counts["onset_speed_median"] = float(np.median(s)) if s.size else 0.0
    counts["onset_speed_max"] = float(s.max()) if s.size else 0.0
    counts["env_steps"] = done
    return counts


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=3000, help="env-steps per policy class")
    args = p.parse_args()
    env = GYM_TARGETS["gym Pusher-v5"].make("viability", max_episode_steps=200)
    rows = {cls: run_class(env, cls, args.steps) for cls in CLASSES}
    total = {k: sum(r[k] for r in rows.values()) for k in KINDS + ("violating", "saturated", "onsets", "env_steps")}
    print(f"Gymnasium Pusher-v5 under JointLimitShieldWrapper(v_max=2.0), {args.steps} env-steps per class")
    head = ("class", "violating") + KINDS + ("saturated", "onsets", "median [m/s]", "fastest [m/s]")
    print(" | ".join(head))
    for cls, r in rows.items():
        cells = [cls, r["violating"], *(r[k] for k in KINDS), r["saturated"], r["onsets"]]
        print(" | ".join(map(str, cells)) + f" | {r['onset_speed_median']:.3f} | {r['onset_speed_max']:.3f}")
    print("JSON " + json.dumps({"classes": rows, "total": total}))


if __name__ == "__main__":
    main()
