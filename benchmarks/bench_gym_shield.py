"""Cost of ``JointLimitShieldWrapper`` on Gymnasium's Pusher-v5 (C MuJoCo, Euler, 5 substeps per step).

    .venv/bin/python benchmarks/bench_gym_shield.py                # 3000 timed steps per variant and round, 5 rounds
    .venv/bin/python benchmarks/bench_gym_shield.py --steps 600 --repeats 3

Variants, each its own ``gymnasium.make("Pusher-v5").unwrapped`` (no ``TimeLimit``/checker wrappers, so the
difference is the shield alone): ``pusher`` (the env's own ``step``) and ``shielded``
(``JointLimitShieldWrapper(env, v_max=2.0)``, method ``"viability"``). Random actions, uniform in the action box,
drawn up front, the same for both; a reset every 200 steps (not timed); ``--warmup`` steps first. The rounds
interleave the variants (order alternated each round) so that a change of load on a shared machine hits both;
reported: the median over rounds of the microseconds per ``env.step`` and the overhead
``median(shielded) / median(pusher) - 1``.

Breakdown of one shielded step, measured in place (one more run over the same actions with timing shims around
the pieces): the jitted decision (one XLA call, ``jl.acc_bounds`` + projection, float32 numpy in, one packed
array out), ``CActuation.smooth_stage`` and ``finish_substep`` (``frame_skip`` of each per step), and the rest
(the wrapper's bookkeeping, the env's observation and reward) as the difference; for scale, the plain env's
``frame_skip`` ``mj_step`` calls.

Prints a table and, last, ONE JSON line ``{"pusher_us": ..., "shielded_us": ..., "overhead": ...}``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import jaxlimits.envs  # noqa: F401  (XLA CPU flags before JAX starts)

import gymnasium
import mujoco
import numpy as np

from jaxlimits.envs.gym_shield import JointLimitShieldWrapper

EPISODE = 200


def _make(shielded: bool):
    env = gymnasium.make("Pusher-v5").unwrapped
    if not shielded:
        return env
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the torque-derived a_max's quantile warning
        return JointLimitShieldWrapper(env, v_max=2.0)


def _run(env, actions, seed: int) -> float:
    """Microseconds per ``env.step`` over ``actions`` (resets every ``EPISODE`` steps, not timed)."""
    total = 0.0
    for start in range(0, len(actions), EPISODE):
        env.reset(seed=seed + start)
        chunk = actions[start : start + EPISODE]
        t0 = time.perf_counter()
        for a in chunk:
            env.step(a)
        total += time.perf_counter() - t0
    return total / len(actions) * 1e6


def _breakdown(env: JointLimitShieldWrapper, actions) -> dict:
    """Microseconds per step spent in the decision, ``smooth_stage`` and ``finish_substep``, measured in place
    (timing shims around them for one more run over ``actions``; the shims' own cost, ~0.2 us a call, is in)."""
    base = env.unwrapped
    act = env.actuation
    spent = {"decision": 0.0, "smooth_stage": 0.0, "finish_substep": 0.0}

    def timed(name, fn):
        def shim(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            spent[name] += time.perf_counter() - t0
            return out

        return shim

    decide, compiled = env._deciders[base.frame_skip]
    env._deciders[base.frame_skip] = (decide, timed("decision", lambda *a: np.asarray(compiled(*a))))
    act.smooth_stage = timed("smooth_stage", act.smooth_stage)
    act.finish_substep = timed("finish_substep", act.finish_substep)
    try:
        total = _run(env, actions, seed=99)
    finally:
        env._deciders[base.frame_skip] = (decide, compiled)
        del act.smooth_stage, act.finish_substep
    out = {k: v / len(actions) * 1e6 for k, v in spent.items()}
    out["total"] = total
    m, d = base.model, base.data
    t0 = time.perf_counter()
    for _ in range(len(actions)):
        mujoco.mj_step(m, d)
    out["mj_step"] = (time.perf_counter() - t0) / len(actions) * 1e6
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=3000, help="timed steps per variant and round")
    p.add_argument("--repeats", type=int, default=5, help="interleaved rounds")
    p.add_argument("--warmup", type=int, default=400)
    args = p.parse_args()

    build, built = {}, {}
    for name, shielded in (("plain", False), ("first", True), ("alike", True)):
        t0 = time.perf_counter()
        built[name] = _make(shielded)
        build[name] = time.perf_counter() - t0
    built.pop("alike").close()  # timed only: an alike wrapper shares the first one's compiled decision
    envs = {"pusher": built["plain"], "shielded": built["first"]}
    rng = np.random.default_rng(0)
    space = envs["pusher"].action_space
    actions = rng.uniform(space.low, space.high, size=(args.steps, space.shape[0]))
    for env in envs.values():
        _run(env, actions[: args.warmup], seed=1)
    times = {k: [] for k in envs}
    for r in range(args.repeats):
        order = list(envs) if r % 2 == 0 else list(envs)[::-1]
        for k in order:
            times[k].append(_run(envs[k], actions, seed=1000 * r))
    med = {k: float(np.median(v)) for k, v in times.items()}
    overhead = med["shielded"] / med["pusher"] - 1.0

    shielded = envs["shielded"]
    n_frames = shielded.unwrapped.frame_skip
    parts = _breakdown(shielded, actions)
    print(f"Pusher-v5, frame_skip {n_frames}, {args.steps} random-action steps x {args.repeats} interleaved rounds")
    print(f"{'variant':10s} {'median us/step':>15s} {'rounds':>40s}")
    for k in envs:
        print(f"{k:10s} {med[k]:15.1f} {' '.join(f'{t:.0f}' for t in times[k]):>40s}")
    print(f"overhead {overhead:+.1%} (target <= +15 %)")
    print(f"\nbreakdown of one shielded step [us] (in place, one instrumented run: {parts['total']:.0f} us/step):")
    rows = [
        ("jitted decision (1 per step, incl. to numpy)", parts["decision"]),
        (f"CActuation.smooth_stage x {n_frames}", parts["smooth_stage"]),
        (f"CActuation.finish_substep x {n_frames}", parts["finish_substep"]),
    ]
    rows.append(("rest (wrapper bookkeeping, env obs/reward)", parts["total"] - sum(r[1] for r in rows)))
    rows.append((f"(plain env's physics: mj_step x {n_frames})", parts["mj_step"] * n_frames))
    for name, us in rows:
        print(f"  {name:42s} {us:8.1f}")
    print(
        f"\nbuild [s]: unwrapped env {build['plain']:.2f}, first shielded {build['first']:.2f} (traces and compiles "
        f"the decision), an alike one {build['alike']:.2f} (shares it: {build['first'] / build['alike']:.0f}x less)"
    )
    print(
        json.dumps(
            {
                "pusher_us": round(med["pusher"], 2),
                "shielded_us": round(med["shielded"], 2),
                "overhead": round(overhead, 4),
                "build_plain_s": round(build["plain"], 3),
                "build_first_s": round(build["first"], 3),
                "build_alike_s": round(build["alike"], 3),
            }
        )
    )


if __name__ == "__main__":
    main()
