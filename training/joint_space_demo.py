"""Del Prete 2018, Sec. V-A / Fig. 4: one joint under a PD controller driven past its upper limit.

The desired acceleration ``kp (q_ref - q) - kd v`` (eq. 32, ``q_ref = q_max + 0.1``) is projected
onto the bounds of each method (eq. 31, for one joint a clip) and the joint is simulated with the
chosen discretisation. The table reports the largest position and velocity violations measured in
simulation: continuous time for ``zoh``, every substep for ``semi_implicit``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxlimits as jl


@dataclass(frozen=True)
class Scenario:
    """The paper's numbers: k_p = 1000, k_d = 2 sqrt(k_p), dt = 0.01 s, q_max = 2, v_max = 2, a_max = 12."""

    kp: float = 1000.0
    dt: float = 0.01
    q_min: float = -2.0
    q_max: float = 2.0
    v_max: float = 2.0
    a_max: float = 12.0
    q0: float = 0.0
    overshoot: float = 0.1
    duration: float = 1.5

    @property
    def kd(self) -> float:
        return 2.0 * math.sqrt(self.kp)

    @property
    def limits(self) -> jl.JointLimits:
        return jl.JointLimits(self.q_min, self.q_max, self.v_max, self.a_max)


@dataclass(frozen=True)
class Variant:
    """One row of the experiment: which bounds, computed for which model, simulated how."""

    label: str
    method: str
    bounds_integrator: str = "zoh"
    sim_integrator: str = "zoh"
    substeps: int = 1
    dt_factor: float = 1.0  # bounds computed with dt_factor * dt (Fig. 4b, 4d)


VARIANTS = (
    Variant("naive", "naive"),
    Variant("naive, 5x dt", "naive", dt_factor=5.0),
    Variant("viability", "viability"),
    Variant("viability, 2x dt", "viability", dt_factor=2.0),
    Variant("viability zoh in MuJoCo-like sim", "viability", "zoh", "semi_implicit", 5),
    Variant("viability semi_implicit", "viability", "semi_implicit", "semi_implicit", 5),
)


def simulate(scenario: Scenario, variant: Variant):
    """Run one variant; returns a dict of arrays ``t, q, v, a, lower, upper, q_high, q_low`` (steps,)."""
    lim = scenario.limits
    q_ref = scenario.q_max + scenario.overshoot
    steps = int(round(scenario.duration / scenario.dt))

    def step(state, _):
        q, v = state
        b = jl.acc_bounds(
            q,
            v,
            lim,
            scenario.dt * variant.dt_factor,
            method=variant.method,
            integrator=variant.bounds_integrator,
            substeps=variant.substeps if variant.bounds_integrator == "semi_implicit" else 1,
        )
        a_des = scenario.kp * (q_ref - q) - scenario.kd * v
        a = jnp.clip(a_des, b.lower, b.upper)
        nxt = jl.integrate_step(
            q,
            v,
            a,
            scenario.dt,
            variant.sim_integrator,
            variant.substeps if variant.sim_integrator == "semi_implicit" else 1,
        )
        return (nxt.q, nxt.v), dict(q=q, v=v, a=a, lower=b.lower, upper=b.upper, q_high=nxt.q_high, q_low=nxt.q_low)

    init = (jnp.float32(scenario.q0), jnp.float32(0.0))
    _, trace = jax.jit(lambda s: jax.lax.scan(step, s, None, length=steps))(init)
    out = {k: np.asarray(x, dtype=np.float64) for k, x in trace.items()}
    out["t"] = np.arange(steps) * scenario.dt
    return out


def violations(scenario: Scenario, trace) -> dict:
    """Largest position [rad] and velocity [rad/s] violation over the run (0.0 when none)."""
    pos = max(0.0, float(np.max(trace["q_high"] - scenario.q_max)), float(np.max(scenario.q_min - trace["q_low"])))
    vel = max(0.0, float(np.max(np.abs(trace["v"]) - scenario.v_max)))
    hit = np.flatnonzero(trace["q_high"] >= scenario.q_max - 1e-3)
    return {
        "max_position_violation": pos,
        "max_velocity_violation": vel,
        "max_abs_acceleration": float(np.max(np.abs(trace["a"]))),
        "first_reach_time": float(trace["t"][hit[0]]) if hit.size else None,
        "speed_at_limit": float(abs(trace["v"][hit[0] + 1])) if hit.size and hit[0] + 1 < len(trace["v"]) else None,
    }


def run(out_dir: str | Path, scenario: Scenario = Scenario(), variants=VARIANTS, plot: bool = True) -> list[dict]:
    """Run every variant, print the table, write ``results.json`` (and ``joint_space.png``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows, traces = [], {}
    for variant in variants:
        trace = simulate(scenario, variant)
        traces[variant.label] = trace
        rows.append({**asdict(variant), **violations(scenario, trace)})
    print(format_table(rows))
    (out / "results.json").write_text(json.dumps({"scenario": asdict(scenario), "rows": rows}, indent=2))
    if plot:
        plot_traces(scenario, traces, out / "joint_space.png")
    return rows


def format_table(rows) -> str:
    head = f"{'method':34s} {'bounds model':>14s} {'simulated as':>14s} {'max pos viol [rad]':>19s} {'max vel viol [rad/s]':>21s}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['label']:34s} {r['bounds_integrator']:>14s} {r['sim_integrator']:>14s} "
            f"{r['max_position_violation']:19.3e} {r['max_velocity_violation']:21.3e}"
        )
    return "\n".join(lines)


def plot_traces(scenario: Scenario, traces, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [lab for lab in ("naive", "naive, 5x dt", "viability", "viability, 2x dt") if lab in traces]
    fig, axes = plt.subplots(3, len(labels), figsize=(4 * len(labels), 8), sharex=True, squeeze=False)
    for col, label in enumerate(labels):
        tr = traces[label]
        ax_q, ax_v, ax_a = axes[:, col]
        ax_q.plot(tr["t"], tr["q"], label="q")
        ax_q.plot(tr["t"], tr["q_high"], lw=0.8, alpha=0.6, label="max q in step")
        ax_q.axhline(scenario.q_max, color="k", ls="--", lw=1)
        ax_q.set_ylim(scenario.q_max - 1.0, scenario.q_max + 0.3)
        ax_q.set_title(label)
        ax_v.plot(tr["t"], tr["v"])
        for s in (-1, 1):
            ax_v.axhline(s * scenario.v_max, color="k", ls="--", lw=1)
        ax_a.plot(tr["t"], tr["a"], label="a")
        ax_a.plot(tr["t"], tr["lower"], lw=0.8, ls=":", label="lower")
        ax_a.plot(tr["t"], tr["upper"], lw=0.8, ls=":", label="upper")
        ax_a.set_xlabel("t [s]")
        if col == 0:
            ax_q.set_ylabel("q [rad]")
            ax_v.set_ylabel("v [rad/s]")
            ax_a.set_ylabel("a [rad/s²]")
            ax_q.legend(fontsize=7)
            ax_a.legend(fontsize=7)
    fig.suptitle("One joint, PD toward q_max + 0.1 rad (Del Prete 2018, Fig. 4)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
