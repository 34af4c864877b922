"""Throughput of ``jl.acc_bounds`` (jitted) in joint-bounds per second, against plain scalar Python.

Usage::

    .venv/bin/python benchmarks/bench_bounds.py            # full run, ~2-3 min on a 2-core CPU
    .venv/bin/python benchmarks/bench_bounds.py --quick    # tiny batches, few repeats, < 30 s

A *joint-bound* is one joint's ``(lower, upper, viable)`` for one state, so a batch of shape
``(B, 7)`` is ``7 B`` joint-bounds. Configurations: ``method="viability"`` with the zero-order
hold (the paper's model), ``viability`` with ``integrator="semi_implicit", substeps=5`` (MuJoCo at
dt = 0.01 s, timestep 2 ms) and ``method="naive"`` (eq. 2), each in float32 and float64 (float64
inside ``jax.enable_x64(True)``), for batch shapes (1,7) ... (1000000,7). Limits are a Franka
Panda's; states are viable, half uniform over the viable set, half near a position limit (1 um to
10 cm away) with speeds up to the viability curve, so every branch of the formulas is taken.

Timing: one jitted function per configuration, compiled and run once (warm-up), then timed
samples of ``inner`` back-to-back calls ending in ``block_until_ready`` (``inner`` chosen so that a
sample lasts >= ~0.1 s in the full run); the figure is the median over samples. The machine may be
shared: each sample also measures the CPU time other processes used meanwhile (``/proc/stat``
minus this process), samples during which another process took more than 10 % of a core are
discarded and redrawn (up to a time budget), and the number discarded is reported
(``contended_samples``; a figure marked ``*`` had no clean sample).

Scalar reference: ``benchmarks/scalar_reference.py`` (plain Python, ``math`` only, one joint at a
time) timed in the same run on a sample of the same states, extrapolated to joints/s.

Profile (full run, float32, largest batch): the bounds against the memory-bandwidth floor (a
jitted ``jnp.clip`` with the same inputs and outputs: two float arrays in, two float arrays and a
bool array out), against ``naive``, and with the outputs consumed inside the same jit
(``jnp.clip(a, lower, upper)``, one output), which shows what the standalone three-output call
costs in fusion. XLA flag pass: the script re-runs itself (``--child``) with
``XLA_FLAGS=--xla_cpu_use_fusion_emitters=false`` (set by the project for MuJoCo-MJX) and without
it, measuring float32 viability/zoh at the largest batch in each.

Headline for the MuJoCo model: float32 ``viability/semi_implicit(5)`` against ``viability/zoh`` at
batch (131072, 7), both from the same run, with their ratio (``semi_implicit5_vs_zoh_float32``
in the JSON; goal >= 100 M joint-bounds/s and >= 0.5x zoh; ``--quick`` reports its largest batch).
The profile also counts the XLA fusions of ``viability/semi_implicit(5)``.

The last line of the output is ``JSON {...}`` with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
FLAG = "--xla_cpu_use_fusion_emitters=false"

# Franka Emika Panda joint limits (rad, rad/s, rad/s^2); condition (11) holds at dt = 0.01 s.
Q_MIN = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
Q_MAX = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
V_MAX = [2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61]
A_MAX = [15.0, 7.5, 10.0, 12.5, 15.0, 20.0, 20.0]
DT = 0.01
N_JOINTS = 7

CONFIGS = {  # name: (method, integrator, substeps)
    "viability/zoh": ("viability", "zoh", 1),
    "viability/semi_implicit(5)": ("viability", "semi_implicit", 5),
    "naive/zoh": ("naive", "zoh", 1),
}
FULL_BATCHES = [1, 64, 1024, 16384, 131072, 1_000_000]
QUICK_BATCHES = [1, 256]
GOAL_RATE = 100e6  # joint-bounds/s, float32 (viability/zoh, and viability/semi_implicit(5) at HEADLINE_BATCH)
HEADLINE_BATCH = 131072  # semi_implicit(5) vs zoh is reported here (--quick: at its largest batch)
GOAL_SEMI_VS_ZOH = 0.5  # viability/semi_implicit(5) at least half as fast as viability/zoh, same run


# ---------------------------------------------------------------- contention-aware timing


def _busy_seconds() -> float:
    """CPU seconds all processes spent busy since boot (``/proc/stat``); NaN where unavailable."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:9]]
    except OSError:
        return float("nan")
    return (sum(fields) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")


class CpuWatch:
    """Wall time of a block and the CPU time *other* processes used during it."""

    def __enter__(self):
        self._busy, self._own, self._wall = _busy_seconds(), sum(os.times()[:4]), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.wall = time.perf_counter() - self._wall
        own = sum(os.times()[:4]) - self._own
        self.foreign = max(_busy_seconds() - self._busy - own, 0.0)  # NaN-safe: max(nan, 0) is nan
        return False

    @property
    def clean(self) -> bool:
        # 10 % of a core, plus one clock tick of /proc/stat's granularity
        return not (self.foreign > 0.1 * self.wall + 1.0 / os.sysconf("SC_CLK_TCK"))


class Timer:
    """Median rate of a callable over clean samples; counts the samples discarded for contention."""

    def __init__(self, samples: int, sample_s: float, budget_s: float, total_redraw_s: float = 40.0):
        self.samples, self.sample_s, self.budget_s = samples, sample_s, budget_s
        self.total_redraw_s = total_redraw_s  # over the whole run, so a busy machine cannot stall it
        self.redraw_s = 0.0
        self.contended_total = 0

    def rate(self, run, work: float) -> dict:
        """``run(k)`` does ``k`` calls and blocks; ``work`` units per call. Returns rate and stats."""
        run(1)  # warm-up (compilation happened before)
        t0 = time.perf_counter()
        run(1)
        one = max(time.perf_counter() - t0, 1e-7)
        inner = max(1, int(self.sample_s / one))
        clean, dirty = [], []
        deadline = time.perf_counter() + self.budget_s
        while len(clean) < self.samples:
            with CpuWatch() as w:
                run(inner)
            (clean if w.clean else dirty).append(inner * work / w.wall)
            if not w.clean:
                self.redraw_s += w.wall
            out_of_time = time.perf_counter() > deadline or self.redraw_s > self.total_redraw_s
            if out_of_time and len(clean) + len(dirty) >= self.samples:
                break
        self.contended_total += len(dirty)
        use = clean if clean else dirty
        return {
            "rate": statistics.median(use),
            "samples": len(use),
            "contended_samples": len(dirty),
            "clean": bool(clean),
            "inner": inner,
        }


# ---------------------------------------------------------------- states


def make_states(batch: int, seed: int = 0):
    """Viable float64 states ``(batch, 7)``: half uniform over the viable set, half near a limit."""
    import numpy as np

    rng = np.random.default_rng(seed)
    q_min, q_max, v_max, a_max = (np.asarray(x) for x in (Q_MIN, Q_MAX, V_MAX, A_MAX))
    shape = (batch, N_JOINTS)
    span = q_max - q_min
    q = rng.uniform(q_min, q_max, shape)
    near = rng.random(shape) < 0.5
    side = np.where(rng.random(shape) < 0.5, 1.0, -1.0)
    d = span * 10.0 ** rng.uniform(-6.0, -1.0, shape)
    q = np.where(near, np.where(side > 0, q_max - d, q_min + d), q)
    v_up = np.minimum(v_max, np.sqrt(2.0 * a_max * np.maximum(q_max - q, 0.0)))  # fastest viable toward q_max
    v_dn = np.minimum(v_max, np.sqrt(2.0 * a_max * np.maximum(q - q_min, 0.0)))
    u = rng.uniform(-1.0, 1.0, shape)
    u = np.where(near & (rng.random(shape) < 0.5), side * rng.uniform(0.9, 1.0, shape), u)  # ride the curve
    v = np.where(u >= 0, u * v_up, u * v_dn)
    return q, v


# ---------------------------------------------------------------- scalar reference


def scalar_rates(n_joints: int, repeats: int) -> dict:
    """Joint-bounds/s of the plain-Python reference on ``n_joints`` of the same states (median)."""
    import numpy as np

    sys.path.insert(0, str(HERE))
    from scalar_reference import scalar_bounds

    q, v = make_states(-(-n_joints // N_JOINTS), seed=1)
    cols = np.arange(q.size) % N_JOINTS
    rows = list(zip(q.ravel().tolist(), v.ravel().tolist(), cols.tolist()))[:n_joints]
    lims = list(zip(Q_MIN, Q_MAX, V_MAX, A_MAX))
    out = {}
    for name, (method, integrator, substeps) in CONFIGS.items():
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for qi, vi, j in rows:
                scalar_bounds(qi, vi, *lims[j], DT, method=method, integrator=integrator, substeps=substeps)
            times.append(time.perf_counter() - t0)
        out[name] = len(rows) / statistics.median(times)
    return out


# ---------------------------------------------------------------- JAX measurements


def _jax_runner(fn, args):
    import jax

    def run(k):
        out = None
        for _ in range(k):
            out = fn(*args)
        jax.block_until_ready(out)

    return run


def bounds_fn(config: str, limits):
    import jax

    import jaxlimits as jl

    method, integrator, substeps = CONFIGS[config]
    return jax.jit(
        lambda q, v: jl.acc_bounds(q, v, limits, DT, method=method, integrator=integrator, substeps=substeps)
    )


def measure_all(batches, timer: Timer, limits) -> list[dict]:
    import jax
    import jax.numpy as jnp

    rows = []
    for dtype_name, x64 in (("float32", False), ("float64", True)):
        with jax.enable_x64(x64):
            dtype = jnp.float64 if x64 else jnp.float32
            for batch in batches:
                qn, vn = make_states(batch)
                q, v = jnp.asarray(qn, dtype), jnp.asarray(vn, dtype)
                for config in CONFIGS:
                    fn = bounds_fn(config, limits)
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(q, v))
                    compile_s = time.perf_counter() - t0
                    r = timer.rate(_jax_runner(fn, (q, v)), batch * N_JOINTS)
                    rows.append(
                        {
                            "config": config,
                            "dtype": dtype_name,
                            "batch": [batch, N_JOINTS],
                            "compile_s": round(compile_s, 3),
                            **r,
                        }
                    )
                del q, v
    return rows


def profile(batch: int, timer: Timer, limits) -> dict:
    """float32, largest batch: what limits the standalone call (see module docstring)."""
    import jax
    import jax.numpy as jnp

    import jaxlimits as jl

    qn, vn = make_states(batch)
    q, v = jnp.asarray(qn, jnp.float32), jnp.asarray(vn, jnp.float32)
    a = jnp.asarray(qn[::-1] * 3.0, jnp.float32)
    lo = jnp.asarray(Q_MIN, jnp.float32)
    hi = jnp.asarray(Q_MAX, jnp.float32)
    vm = jnp.asarray(V_MAX, jnp.float32)

    def bounds(q, v):
        return jl.acc_bounds(q, v, limits, DT)

    cases = {
        "viability/zoh (lower, upper, viable)": (jax.jit(bounds), (q, v)),
        "viability/zoh (lower, upper) only": (jax.jit(lambda q, v: tuple(bounds(q, v)[:2])), (q, v)),
        "viability/zoh fused: clip(a, lower, upper)": (
            jax.jit(lambda q, v, a: jnp.clip(a, *bounds(q, v)[:2])),
            (q, v, a),
        ),
        "naive/zoh (lower, upper, viable)": (bounds_fn("naive/zoh", limits), (q, v)),
        "semi_implicit(5) (lower, upper, viable)": (bounds_fn("viability/semi_implicit(5)", limits), (q, v)),
        "floor: jnp.clip, same I/O": (
            jax.jit(lambda q, v: (jnp.clip(q, lo, hi), jnp.clip(v, -vm, vm), q < hi)),
            (q, v),
        ),
        "floor: jnp.clip(q), 1 in 1 out": (jax.jit(lambda q: jnp.clip(q, lo, hi)), (q,)),
    }
    out = {}
    for name, (fn, args) in cases.items():
        jax.block_until_ready(fn(*args))
        txt = fn.lower(*args).compile().as_text()
        entry = txt[txt.index("ENTRY") :]
        r = timer.rate(_jax_runner(fn, args), batch * N_JOINTS)
        r["xla_fusions"] = sum(1 for line in entry.splitlines() if " fusion(" in line)
        out[name] = r
    return out


# ---------------------------------------------------------------- XLA flag pass (child processes)


def child_main(batch: int, samples: int, sample_s: float) -> None:
    import jax
    import jax.numpy as jnp

    import jaxlimits as jl

    limits = jl.JointLimits(Q_MIN, Q_MAX, V_MAX, A_MAX)
    qn, vn = make_states(batch)
    q, v = jnp.asarray(qn, jnp.float32), jnp.asarray(vn, jnp.float32)
    fn = bounds_fn("viability/zoh", limits)
    jax.block_until_ready(fn(q, v))
    r = Timer(samples, sample_s, budget_s=20.0).rate(_jax_runner(fn, (q, v)), batch * N_JOINTS)
    r["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    print("CHILD " + json.dumps(r))


def flag_pass(batch: int, samples: int, sample_s: float) -> dict:
    out = {}
    base = " ".join(
        p
        for p in os.environ.get("XLA_FLAGS", "").split()
        if not p.lstrip("-").startswith("xla_cpu_use_fusion_emitters")
    )
    for label, flags in (("without_flag", base), ("with_flag", (base + " " + FLAG).strip())):
        env = dict(os.environ, XLA_FLAGS=flags)
        cmd = [
            sys.executable,
            str(Path(__file__).resolve()),
            "--child",
            "--child-batch",
            str(batch),
            "--child-samples",
            str(samples),
            "--child-sample-s",
            str(sample_s),
        ]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("CHILD ")]
        if proc.returncode != 0 or len(lines) != 1:
            raise RuntimeError(f"child {label} failed (rc={proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
        out[label] = json.loads(lines[0][len("CHILD ") :])
    return out


# ---------------------------------------------------------------- report


def semi_vs_zoh(rows: list[dict], batch: int = HEADLINE_BATCH) -> dict:
    """float32 ``viability/semi_implicit(5)`` against ``viability/zoh`` at ``batch``, both from this run.

    Where ``batch`` was not measured (``--quick``) the largest measured batch below it is used.
    """
    f32 = [r for r in rows if r["dtype"] == "float32"]
    b = max((r["batch"][0] for r in f32 if r["batch"][0] <= batch), default=min(r["batch"][0] for r in f32))
    rate = {r["config"]: r for r in f32 if r["batch"][0] == b}
    semi, zoh = rate["viability/semi_implicit(5)"], rate["viability/zoh"]
    ratio = semi["rate"] / zoh["rate"]
    return {
        "batch": [b, N_JOINTS],
        "semi_implicit5_rate": semi["rate"],
        "zoh_rate": zoh["rate"],
        "ratio": ratio,
        "clean": semi["clean"] and zoh["clean"],
        "goal_rate": GOAL_RATE,
        "goal_ratio": GOAL_SEMI_VS_ZOH,
        "meets_goal": semi["rate"] >= GOAL_RATE and ratio >= GOAL_SEMI_VS_ZOH,
    }


def fmt_rate(r: float) -> str:
    if r >= 1e9:
        return f"{r / 1e9:7.2f} G"
    if r >= 1e6:
        return f"{r / 1e6:7.2f} M"
    if r >= 1e3:
        return f"{r / 1e3:7.2f} k"
    return f"{r:7.2f}  "


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny batches, few repeats (< 30 s)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--child-batch", type=int, default=1_000_000, help=argparse.SUPPRESS)
    ap.add_argument("--child-samples", type=int, default=5, help=argparse.SUPPRESS)
    ap.add_argument("--child-sample-s", type=float, default=0.3, help=argparse.SUPPRESS)
    ap.add_argument("--no-flag-pass", action="store_true", help="skip the XLA_FLAGS child processes")
    args = ap.parse_args()
    if args.child:
        child_main(args.child_batch, args.child_samples, args.child_sample_s)
        return

    t_start = time.perf_counter()
    load_start = os.getloadavg()
    with CpuWatch() as whole:
        import jax

        import jaxlimits as jl

        quick = args.quick
        batches = QUICK_BATCHES if quick else FULL_BATCHES
        timer = Timer(
            samples=2 if quick else 5,
            sample_s=0.02 if quick else 0.1,
            budget_s=0.5 if quick else 4.0,
            total_redraw_s=3.0 if quick else 40.0,
        )
        limits = jl.JointLimits(Q_MIN, Q_MAX, V_MAX, A_MAX)

        scalar = scalar_rates(2000 if quick else 20000, repeats=1 if quick else 3)
        rows = measure_all(batches, timer, limits)
        prof = profile(batches[-1], timer, limits)
        flags = None
        if not args.no_flag_pass:
            flags = flag_pass(batches[-1], 2 if quick else 5, 0.02 if quick else 0.3)

    for row in rows:
        row["ratio_vs_scalar_python"] = row["rate"] / scalar[row["config"]]

    # ------------------------------------------------ table
    print(
        f"jaxlimits acc_bounds throughput  (jax {jax.__version__}, {jax.default_backend()}, "
        f"{os.cpu_count()} CPUs, XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}, dt={DT}, Panda limits)"
    )
    print("joint-bounds/s = 7 * batch / median time of one jitted call; ratio = vs scalar Python, same config\n")
    print(f"scalar Python reference (benchmarks/scalar_reference.py, {2000 if quick else 20000} joints):")
    for name, r in scalar.items():
        print(f"  {name:28s} {fmt_rate(r)}joint-bounds/s")
    print()
    hdr = f"{'config':28s} {'dtype':8s} {'batch':>13s} {'joint-bounds/s':>15s} {'x scalar Py':>12s} {'compile s':>9s}"
    print(hdr)
    print("-" * len(hdr))
    for row in rows:
        mark = "" if row["clean"] else " *"
        batch = f"({row['batch'][0]},{row['batch'][1]})"
        print(
            f"{row['config']:28s} {row['dtype']:8s} {batch:>13s} {fmt_rate(row['rate']):>13s}/s "
            f"{row['ratio_vs_scalar_python']:11.1f}x {row['compile_s']:9.2f}{mark}"
        )
    print(f"\nprofile, float32, batch ({batches[-1]},7):")
    for name, r in prof.items():
        print(
            f"  {name:44s} {fmt_rate(r['rate'])}joint-bounds/s  ({r['xla_fusions']} XLA fusions)"
            + ("" if r["clean"] else " *")
        )
    if flags:
        print(f"\nXLA flag pass, viability/zoh float32 batch ({batches[-1]},7), fresh process each:")
        for label, r in flags.items():
            print(
                f"  {label:14s} XLA_FLAGS={r['xla_flags']!r:45s} {fmt_rate(r['rate'])}joint-bounds/s"
                + ("" if r["clean"] else " *")
            )
    best32 = max((r for r in rows if r["dtype"] == "float32"), key=lambda r: r["rate"])
    best32_via = max(
        (r for r in rows if r["dtype"] == "float32" and r["config"] == "viability/zoh"), key=lambda r: r["rate"]
    )
    goal = GOAL_RATE
    semi = semi_vs_zoh(rows)
    print(
        f"\nviability/semi_implicit(5) float32 batch {tuple(semi['batch'])}: {fmt_rate(semi['semi_implicit5_rate'])}"
        f"joint-bounds/s = {semi['ratio']:.2f} x viability/zoh ({fmt_rate(semi['zoh_rate'])}joint-bounds/s, same run; "
        f"goal >= {GOAL_RATE / 1e6:.0f} M and >= {GOAL_SEMI_VS_ZOH} x: {'met' if semi['meets_goal'] else 'not met'})"
        + ("" if semi["clean"] else " *")
    )
    print(
        f"best float32: {fmt_rate(best32['rate'])}joint-bounds/s ({best32['config']}, batch {best32['batch']}); "
        f"viability/zoh: {fmt_rate(best32_via['rate'])}joint-bounds/s "
        f"({'meets' if best32_via['rate'] >= goal else 'below'} the 100 M goal)"
    )
    n_dirty = timer.contended_total
    print(
        f"samples discarded because another process used the CPU: {n_dirty}; "
        f"other processes' CPU time during the run: {whole.foreign:.1f} s of {whole.wall:.1f} s wall "
        "(figures marked * had no clean sample)"
    )

    result = {
        "jax_version": jax.__version__,
        "backend": jax.default_backend(),
        "cpu_count": os.cpu_count(),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
        "quick": quick,
        "dt": DT,
        "unit": "joint-bounds/s",
        "scalar_python": scalar,
        "results": rows,
        "best_float32": {"rate": best32["rate"], "config": best32["config"], "batch": best32["batch"]},
        "best_float32_viability_zoh": {"rate": best32_via["rate"], "batch": best32_via["batch"]},
        "goal_rate": goal,
        "viability_zoh_meets_goal": best32_via["rate"] >= goal,
        "semi_implicit5_vs_zoh_float32": semi,
        "profile_float32_largest_batch": prof,
        "xla_flag_pass": flags,
        "contended_samples": n_dirty,
        "other_processes_cpu_s": whole.foreign,
        "load_avg_start": load_start,
        "wall_s": time.perf_counter() - t_start,
    }
    print("JSON " + json.dumps(result))


if __name__ == "__main__":
    main()
