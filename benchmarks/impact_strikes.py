"""Randomised wall strikes on the MJX Panda with and without the impact-aware speed caps (Wang & Kheddar).

    .venv/bin/python benchmarks/impact_strikes.py [--strikes 10000] [--chunk 1000] [--steps 70] [--quick]

Each strike: a random start near the home posture, a wall at a random gap (0.5-5 cm) along +x and a
commanded approach speed uniform in [0.05, 1.5] m/s (scripted resolved-rate striker). The same
strikes run through two shields: ``viability`` and ``viability+impact``. Prints a table, the
Panda's maximum feasible contact velocity, a speed-vs-impulsive-torque table, the soft-vs-rigid
ratio, and one JSON line.

``--contact paper`` (default: the paper's reproduction, the README's table) predicts with Wang & Kheddar's
rigid model; ``--contact coulomb`` with the env's default, ``CoulombContact(friction = 1)``: every impulse
in the friction cone (sound for this contact, and more conservative). The home-posture cap of both is printed.
"""

from __future__ import annotations

import argparse
import json
import time

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxlimits as jl  # noqa: E402
import jaxlimits.impact as ji  # noqa: E402
from jaxlimits.envs.safety import SafetyWrapper  # noqa: E402
from jaxlimits.envs.wall_strike import HOME, make_wall_strike, rigid_prediction, strike_experiment  # noqa: E402


def run_strikes(env, shields, strikes, chunk, steps, seed=0):
    """Concatenated per-strike results over chunks (one compilation: same shapes every chunk)."""
    out = {w.name: {} for w in shields}
    for i in range(max(1, strikes // chunk)):
        t = time.time()
        r = strike_experiment(env, shields, chunk, steps, seed=seed + i)
        print(f"chunk {i}: {chunk} strikes per shield in {time.time() - t:.1f} s", flush=True)
        for name, d in r.items():
            for k, v in d.items():
                out[name].setdefault(k, []).append(v)
    return {name: {k: np.concatenate(v) for k, v in d.items()} for name, d in out.items()}


def soft_vs_rigid(env, d):
    """Measured impulsive torque (over its bound, worst joint) / the rigid model's at c = 0 and at c_max."""
    hit = d["hit"] > 0
    tau_b = np.asarray(env.impact.tau_imp_max)
    P0, _ = rigid_prediction(env, d["q_pre"][hit], d["v_pre"][hit], 0.0)
    Pc, _ = rigid_prediction(env, d["q_pre"][hit], d["v_pre"][hit], env.impact.c_range[1])
    pred0 = np.max(np.abs(P0) / env.impact.dt_impact / tau_b, axis=1)
    predc = np.max(np.abs(Pc) / env.impact.dt_impact / tau_b, axis=1)
    meas = d["tau"][hit]
    return meas / np.maximum(pred0, 1e-9), meas / np.maximum(predc, 1e-9), pred0, predc


def summary(env, d):
    hit = d["hit"] > 0
    r0, rc, _, _ = soft_vs_rigid(env, d)
    return {
        "strikes": int(len(hit)),
        "hits": int(hit.sum()),
        "w_mean": float(d["w"][hit].mean()) if hit.any() else 0.0,
        "w_max": float(d["w"][hit].max()) if hit.any() else 0.0,
        "tau_ratio_max": float(d["tau"][hit].max()) if hit.any() else 0.0,
        "tau_violations": int((d["tau"][hit] > 1.0).sum()),
        "v_post_ratio_max": float(d["v_post"][hit].max()) if hit.any() else 0.0,
        "v_post_violations": int((d["v_post"][hit] > 1.0).sum()),
        "position_violations": int((d["violation_position"] > 0).sum()),
        "velocity_violations": int((d["violation_velocity"] > 0).sum()),
        # strikes whose episode asked the motors for more torque than they have: anywhere, and before the first
        # contact (the torque limit's claim; pressing the wall can ask more, counted)
        "torque_violations": int((d["violation_torque"] > 0).sum()),
        "torque_violations_free": int((d["violation_torque_free"] > 0).sum()),
        "torque_excess_max": float(d["violation_torque"].max()),
        "infeasible_steps": int(d["infeasible"].sum()),
        "cap_mean": float(np.mean(d["cap"][np.isfinite(d["cap"])])) if np.isfinite(d["cap"]).any() else float("inf"),
        "meas_over_rigid_c0_median": float(np.median(r0)) if r0.size else 0.0,
        "meas_over_rigid_c0_max": float(r0.max()) if r0.size else 0.0,
        "meas_over_rigid_cmax_max": float(rc.max()) if rc.size else 0.0,
    }


def home_caps(env):
    """The cap at rest at the home posture (``SpeedCap``), and its values over 512 episode start states (home first)."""
    lim = env.limits
    spec = env.impact

    def cap(q):
        M, J, nrm = env.impact_terms(q, jnp.zeros_like(q))
        return jl.impact_speed_cap(
            M,
            J,
            nrm,
            q,
            jnp.zeros_like(q),
            lim,
            spec.tau_imp_max,
            env.dt,
            spec.c_range[1],
            spec.dt_impact,
            contact=spec.contact,
        )

    qs = jnp.asarray(HOME, jnp.float32) + jax.random.uniform(
        jax.random.PRNGKey(0), (512, env.n), jnp.float32, -env.q_noise, env.q_noise
    )
    qs = qs.at[0].set(jnp.asarray(HOME, jnp.float32))  # the home posture first (one compilation)
    cs = jax.jit(jax.vmap(cap))(qs)
    c_home = jax.tree.map(lambda x: x[0], cs)
    return c_home, np.asarray(cs.cap)


def speed_table(env, d_uncapped, d_capped, edges=(0.0, 0.05, 0.08, 0.1, 0.15, 0.2, 0.3, 1.0)):
    rows = []
    for name, d in (("capped", d_capped), ("uncapped", d_uncapped)):
        hit = d["hit"] > 0
        w, tau = d["w"][hit], d["tau"][hit]
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (w >= lo) & (w < hi)
            if sel.sum():
                rows.append((name, lo, hi, int(sel.sum()), float(tau[sel].mean()), float(tau[sel].max())))
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--strikes", type=int, default=10000)
    p.add_argument("--chunk", type=int, default=1000)
    p.add_argument("--steps", type=int, default=70)
    p.add_argument("--margin", type=float, default=1.0)
    p.add_argument("--quick", action="store_true", help="32 strikes (a smoke run)")
    p.add_argument("--contact", choices=("paper", "coulomb"), default="paper", help="the cap's contact model")
    a = p.parse_args(argv)
    if a.quick:
        a.strikes, a.chunk = 32, 32
    t0 = time.time()
    env = make_wall_strike(contact_model=ji.PaperContact() if a.contact == "paper" else None)
    shields = [SafetyWrapper(env, "viability"), SafetyWrapper(env, "viability", impact={"margin": a.margin})]
    res = run_strikes(env, shields, a.strikes, a.chunk, a.steps)
    wall = time.time() - t0
    names = [w.name for w in shields]
    summ = {n: summary(env, res[n]) for n in names}
    c_home, caps = home_caps(env)
    other = make_wall_strike(contact_model=None if a.contact == "paper" else ji.PaperContact())
    c_home_other, caps_other = home_caps(other)

    keys = [
        "strikes",
        "hits",
        "w_mean",
        "w_max",
        "tau_ratio_max",
        "tau_violations",
        "v_post_ratio_max",
        "v_post_violations",
        "position_violations",
        "velocity_violations",
        "torque_violations",
        "infeasible_steps",
        "cap_mean",
        "meas_over_rigid_c0_median",
        "meas_over_rigid_c0_max",
        "meas_over_rigid_cmax_max",
    ]
    print(f"{'':28s}" + "".join(f"{n:>22s}" for n in names))
    for k in keys:
        print(f"{k:28s}" + "".join(f"{summ[n][k]:>22.4g}" for n in names))
    spec = env.impact
    print(
        f"\nbounds: tau_imp_max = {np.round(spec.tau_imp_max, 2).tolist()} N m (motor limits), v_max = "
        f"{np.round(env.limits.v_max, 3).tolist()} rad/s, c in {spec.c_range} (c_max used), dt_impact = {spec.dt_impact} s, "
        f"dt = {env.dt} s"
    )
    print(
        f"max feasible contact velocity at rest, home posture: {float(c_home.cap):.4f} m/s "
        f"(position {float(c_home.position):.3g}, velocity {float(c_home.velocity):.3g}, torque {float(c_home.torque):.4f}); "
        f"over 512 start states: min {caps.min():.4f}, median {np.median(caps):.4f}, max {caps.max():.4f} m/s"
    )
    print(
        f"the same with {other.impact.contact}: home {float(c_home_other.cap):.4f} m/s, over the 512 start states "
        f"{caps_other.min():.4f}-{caps_other.max():.4f} m/s"
    )
    print("\nimpact speed vs measured impulsive torque (worst joint, over its bound)")
    print(f"{'shield':10s}{'w [m/s]':>14s}{'strikes':>9s}{'mean':>8s}{'max':>8s}")
    table = speed_table(env, res[names[0]], res[names[1]])
    for name, lo, hi, cnt, mean, mx in table:
        print(f"{name:10s}{f'[{lo:.2f},{hi:.2f})':>14s}{cnt:>9d}{mean:>8.3f}{mx:>8.3f}")
    print(f"\nwall time {wall:.1f} s")
    print(
        json.dumps(
            {
                "bench": "impact_strikes",
                "strikes": a.strikes,
                "steps": a.steps,
                "margin": a.margin,
                "contact": repr(env.impact.contact),
                "wall_s": round(wall, 1),
                "cap_home": float(c_home.cap),
                "cap_start_min": float(caps.min()),
                "cap_start_median": float(np.median(caps)),
                "other_contact": repr(other.impact.contact),
                "other_cap_home": float(c_home_other.cap),
                "other_cap_start_min": float(caps_other.min()),
                "other_cap_start_max": float(caps_other.max()),
                "results": summ,
                "speed_table": table,
            }
        )
    )
    return summ


if __name__ == "__main__":
    main()
