"""The impact-aware speed cap on a third-party env: Brax ``pusher``'s wrist striking its table.

``JointLimitShield(..., impact=ImpactPoint("r_wrist_roll_link", normal=(0, 0, -1)))`` caps the wrist's downward
speed (Wang & Kheddar: the predicted joint-velocity jumps and impulsive torques of a strike stay within the limits).
Three shields under the adversarial policies of ``shield_rollout`` (targets at the upper bounds, lower bounds,
bang-bang, random), the same start states and actions:

- ``measured``: viability, the cap computed and the approach speed measured, not enforced (the reference; here
  ``impact_infeasible`` counts the steps whose command, unconstrained by the cap, would end over it);
- ``capped``: viability with the cap enforced, the impulsive torque bound the motors' peak torque (2 N m);
- ``capped x10``: the same with a bound ten times that (a gearbox's impact tolerance);
- ``capped near``: ``capped`` only where the wrist could reach the table before being braked toward the cap
  (``ImpactPoint.surface``, ``clearance``): free elsewhere.

Columns: position / velocity-violating env-steps (every substep), steps over the cap (approach speed above
``max(cap_t-1, cap_t)`` by > 1 % + 1 mm/s), strikes (a contact disturbance begins) with their largest approach
speed and how many came over the cap, the strikes as the shield measures them (``measured_strikes``: a window from
the wrist's first contact through its compression, ``envs/strike_record.py``) and those whose impulsive joint torque
exceeded ``tau_imp_max`` (``impact``) with the worst ratio, steps where no command met the cap
(``impact_infeasible``), and the cost of
one batched step against the shield without an impact point (``no point``, timed only), the configurations timed
in alternating rounds (the least of ``--rounds``). Prints a table and one JSON line.

    .venv/bin/python benchmarks/impact_third_party.py [--batch 128] [--steps 200]
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

from jaxlimits.envs import ImpactPoint, JointLimitShield
from jaxlimits.envs.adversarial import shield_rollout

POINT = dict(point="r_wrist_roll_link", normal=(0.0, 0.0, -1.0))
SHIELDS = {
    "measured": dict(enforce=False),
    "capped": {},
    "capped x10": dict(tau_imp_max=20.0),
    # only within reach of the table (its plane at z = -0.325; the wrist's capsules and fingertips reach 0.16 m
    # past the body's origin)
    "capped near": dict(surface=(0.0, 0.0, -0.325), clearance=0.16),
}


def make(options):
    env = brax.envs.get_environment("pusher", backend="mjx")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the braking-capacity quantile warning (tests/test_brax_shield.py)
        return JointLimitShield(env, v_max=2.0, impact=ImpactPoint(**POINT, **options))


def step_timer(env, batch: int, repeats: int = 10):
    """A function timing ``repeats`` batched steps of random actions [s per step] (compiled here, once)."""
    reset, step = jax.jit(jax.vmap(env.reset)), jax.jit(jax.vmap(env.step))
    state = reset(jax.random.split(jax.random.PRNGKey(0), batch))
    actions = jax.random.uniform(jax.random.PRNGKey(1), (repeats + 1, batch, env.action_size), minval=-1, maxval=1)
    jax.block_until_ready(step(state, actions[0]))

    def timed() -> float:
        s = state
        t0 = time.perf_counter()
        for a in actions[1:]:
            s = step(s, a)
        jax.block_until_ready(s)
        return (time.perf_counter() - t0) / repeats

    return timed


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--timing_batch", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    rows, timers = {}, {}
    for name, options in SHIELDS.items():
        env = make(options)
        t0 = time.perf_counter()
        r = shield_rollout(env, args.batch, args.steps)
        r["wall_s"] = time.perf_counter() - t0
        rows[name] = r
        timers[name] = step_timer(env, args.timing_batch)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        timers["no point"] = step_timer(
            JointLimitShield(brax.envs.get_environment("pusher", backend="mjx"), v_max=2.0), args.timing_batch
        )
    samples = {name: [] for name in timers}
    for _ in range(args.rounds):  # alternating rounds: a slower moment of the machine hits every configuration
        for name, timer in timers.items():
            samples[name].append(timer())
    best = {name: min(times) for name, times in samples.items()}
    ref = best["no point"]
    for name, r in rows.items():
        r["step_s"] = best[name]
    keys = ("position", "velocity", "over_cap", "strikes", "strike_over_cap", "impact_infeasible", "impact_active")
    keys += ("measured_strikes", "impact")
    print(f"Brax pusher, {args.batch} envs x {args.steps} steps per shield ({args.batch * args.steps} env-steps)")
    print(f"{'shield':<12}" + "".join(f"{k:>18}" for k in keys) + f"{'max strike m/s':>16}", end="")
    print(f"{'max ratio':>11}{'step cost':>11}")
    for name, r in rows.items():
        cells = "".join(f"{r[f'count/{k}']:>18,}" for k in keys)
        print(
            f"{name:<12}{cells}{r['max/strike_speed']:>16.4f}{r['max/strike_ratio']:>11.3f}{r['step_s'] / ref:>10.2f}x"
        )
    figures = {
        name: {
            **{k: r[f"count/{k}"] for k in keys},
            "max_strike_speed": r["max/strike_speed"],
            "max_strike_ratio": r["max/strike_ratio"],
            "max_impact_speed": r["max/impact_speed"],
            "env_steps": r["env_steps"],
            "step_us_at_batch": 1e6 * r["step_s"],
            "step_cost_vs_no_point": r["step_s"] / ref,
        }
        for name, r in rows.items()
    }
    print(f"no point (timed only): {1e3 * ref:.1f} ms per step of {args.timing_batch} envs")
    summary = {"benchmark": "impact_third_party", "timing_batch": args.timing_batch, "no_point_step_us": 1e6 * ref}
    print(json.dumps({**summary, "rows": figures}))
    return figures


if __name__ == "__main__":
    main()
