"""The README's figures from scripts the rest of the suite does not run, re-measured on reduced runs.

Each test asserts the claimed quantities (never timings: those are only checked positive and finite):

- ``test_paper_vb_naive_overshoots_viability_stops_short``: "Environments, shields and the paper's Sec. V-B
  (MJX)": naive bounds reach the elbow's limit at 0.99 rad/s and overshoot it by 0.195 rad, viability
  bounds stop short of it at a few mrad/s (``envs/paper_vb.py``'s ``run``, dt x1 only, 200 of its 300 steps:
  both closest approaches come before step 170). The README's "3.3 urad short" predates the whole-stop
  rounding guard (0866429): the same run now stops 0.35 mrad short (346 urad at 0.0032 rad/s), which is asserted.
- ``test_impact_home_cap``: "Impact-aware speed caps": the Panda's maximum feasible contact speed 0.085 m/s at
  the home posture, 0.080-0.096 m/s over the 512 start states, constraint (20) binding, (17) allowing 0.46 m/s
  (the paper's contact model), and 0.029 m/s (0.026-0.037) with the env's default ``CoulombContact(1)``
  (``benchmarks/impact_strikes.py``'s ``home_caps``, the full computation: it costs seconds).
- ``test_impact_strikes_reduced``: the same section's strike table (10^4 strikes: capped 0 over the impulsive-
  torque bound, worst ratio 0.955; uncapped 8 892 / 9 959 over, max 2.91), on 128 strikes
  (``impact_strikes.py --strikes 128 --chunk 128``). Its MJX program takes about 2 min of CPU to trace and
  compile, more than this file's budget in the suite, so it runs only with ``JAXLIMITS_README_STRIKES=1``
  (``tests/test_envs_impact.py`` checks capped vs uncapped on a few fast strikes in every run).
- ``test_bench_qp_smoke_accuracy``: "Box-QP projection", the table's max error column (float32 vs the float64
  solution: clip 3e-8, oracle / dense / halfspace 3e-6 to 4e-6), ``bench_qp.py --smoke`` (batch 512).
- ``test_bench_jerk_quick_runs_and_reports_json``, ``test_bench_env_quick_runs_and_reports_json``: "Jerk-aware
  bounds" throughput and "Environments ..." shield cost: every figure there is a timing, so these check that
  ``--quick`` runs end in one JSON line whose rates are positive and whose ratios are the rates' ratios; and
  the non-timing content of ``bench_env`` (the shield's rollouts: no position violation, the unshielded ones
  have some; Alg. 4 in MJX equals the C loop's bounds).

The subprocesses inherit ``XLA_FLAGS`` (``tests/conftest.py`` adds ``--xla_backend_optimization_level=0``) and
the persistent compilation cache from this process's environment, as in ``tests/test_benchmarks.py``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import load_benchmark

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"


def _finite_positive(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def _run_script(*args: str, timeout: int, json_prefix: str = "JSON ") -> dict:
    """Run ``benchmarks/<script> args``; it must exit 0 and end in exactly one JSON line, which is returned."""
    proc = subprocess.run(
        [sys.executable, str(BENCH / args[0]), *args[1:]], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    lines = proc.stdout.rstrip().splitlines()
    json_lines = [line for line in lines if line.startswith(json_prefix) and line[len(json_prefix) :].startswith("{")]
    assert len(json_lines) == 1, proc.stdout[-3000:]
    assert lines[-1] == json_lines[0], proc.stdout[-3000:]
    return json.loads(json_lines[0][len(json_prefix) :])


# ---- Sec. V-B on the Panda ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_paper_vb_naive_overshoots_viability_stops_short():
    from jaxlimits.envs import paper_vb

    _, out = paper_vb.run(steps=200, dt_factors=(1.0,))
    assert set(out) == {"naive/dt_x1", "viability/dt_x1"}
    naive, viab = out["naive/dt_x1"], out["viability/dt_x1"]
    # the README: "Naive bounds reach the limit at 0.99 rad/s and overshoot by 0.195 rad"
    assert naive["min_q_minus_limit"] == pytest.approx(-0.195, rel=0.02), naive
    assert naive["speed_when_crossing"] == pytest.approx(0.99, rel=0.02), naive
    assert naive["steps_past_limit"] > 50, naive
    assert naive["time_at_min_s"] < 1.9, naive  # the closest approach lies inside the reduced run
    # viability: never past the limit, stops short of it (a few tenths of a mrad) at a few mrad/s
    assert viab["steps_past_limit"] == 0 and viab["speed_when_crossing"] == 0.0, viab
    assert 0.0 < viab["min_q_minus_limit"] < 5e-4, viab
    assert viab["speed_at_min"] < 0.01, viab
    assert viab["time_at_min_s"] < 1.9, viab


# ---- impact-aware speed caps ---------------------------------------------------------------------------------
@pytest.mark.slow
def test_impact_home_cap():
    from jaxlimits.envs.wall_strike import make_wall_strike

    import jaxlimits.impact as ji

    strikes = load_benchmark("impact_strikes")
    with jax.numpy_rank_promotion("allow"):  # the script adds HOME (n,) to the (512, n) offsets
        c_home, caps = strikes.home_caps(make_wall_strike(contact_model=ji.PaperContact()))
        c_coulomb, caps_coulomb = strikes.home_caps(make_wall_strike())
    # "with the env's default contact model, CoulombContact(mu = 1): 0.029 m/s at home, 0.026-0.037 over the starts"
    assert float(c_coulomb.cap) == pytest.approx(0.029, abs=1e-3), c_coulomb
    assert float(c_coulomb.cap) == float(c_coulomb.torque)
    assert caps_coulomb.min() == pytest.approx(0.026, abs=1e-3) and caps_coulomb.max() == pytest.approx(0.037, abs=1e-3)
    cap, pos, vel, tor = (float(x) for x in (c_home.cap, c_home.position, c_home.velocity, c_home.torque))
    # "maximum feasible contact velocity 0.085 m/s at the home posture; constraint (20) binds, (17) would allow 0.46"
    assert cap == pytest.approx(0.085, abs=1e-3), c_home
    assert cap == tor and tor < vel < pos, c_home
    assert vel == pytest.approx(0.46, abs=0.01), c_home
    # "0.080-0.096 m/s over 512 start states" (home first)
    assert caps.shape == (512,) and caps[0] == pytest.approx(cap)
    assert caps.min() == pytest.approx(0.080, abs=1e-3) and caps.max() == pytest.approx(0.096, abs=1e-3), (
        caps.min(),
        caps.max(),
    )


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("JAXLIMITS_README_STRIKES") != "1",
    reason="~2 min of CPU (MJX strike program); set JAXLIMITS_README_STRIKES=1 to run",
)
def test_impact_strikes_reduced():
    out = _run_script("impact_strikes.py", "--strikes", "128", "--chunk", "128", timeout=900, json_prefix="")
    assert out["bench"] == "impact_strikes" and out["strikes"] == 128
    free, capped = out["results"]["viability"], out["results"]["viability+impact"]
    for r in (free, capped):
        assert r["strikes"] == 128 and r["hits"] >= 120, r  # the README: 9 959 hits of 10^4
        assert r["position_violations"] == r["velocity_violations"] == r["torque_violations_free"] == 0, r
        # the torque asked for while pressing the wall (WallStrike counts it since the thirty-fourth session) is
        # reported, not claimed: a contact the motors cannot hold
        assert r["v_post_violations"] == 0 and r["v_post_ratio_max"] < 0.5, r  # "within 0.4 v_max either way"
        assert r["meas_over_rigid_cmax_max"] < 1.0, r  # "the c_max = 0.2 headroom covers it (at most 0.963)"
    # caps: "0 / 9 959" over the impulsive-torque bound, worst ratio 0.955; contact speed mean 0.085, max 0.098
    assert capped["tau_violations"] == 0 and 0.85 < capped["tau_ratio_max"] < 1.0, capped
    assert 0.075 < capped["w_mean"] < 0.095 and capped["w_max"] < 0.1, capped
    assert capped["infeasible_steps"] == 0, capped
    # no caps: "8 892 / 9 959" over (89 %), max 2.91; contact speed mean 0.171, max 0.250
    assert free["tau_violations"] > 0.5 * free["hits"] and free["tau_ratio_max"] > 1.5, free
    assert free["w_mean"] > 0.14 and free["w_max"] > 0.2, free
    assert 0.075 <= out["cap_home"] <= 0.1 and 0.075 <= out["cap_start_min"] <= out["cap_home"], out


# ---- box-QP projection: the accuracy column ---------------------------------------------------------------------
@pytest.mark.slow
def test_bench_qp_smoke_accuracy():
    out = _run_script("bench_qp.py", "--smoke", timeout=300)
    assert out["smoke"] is True and out["dtype"] == "float32" and out["n"] == 7 and out["ratios"] == {}
    results = out["results"]
    assert set(results) == {f"{m}@512" for m in ("clip", "oracle", "dense", "halfspace")}
    for name, r in results.items():
        assert all(_finite_positive(r[k]) for k in ("fwd_s", "fwd_bwd_s", "fwd_min_s", "fwd_bwd_min_s")), (name, r)
    # the README's table: clip 3e-8, oracle 3e-6, dense 4e-6, dense + 1 halfspace 4e-6 (float32 vs float64)
    assert results["clip@512"]["max_err"] <= 1e-7, results
    for m in ("oracle", "dense", "halfspace"):
        assert results[f"{m}@512"]["max_err"] <= 1e-5, (m, results)


# ---- throughput scripts: timings only, and the non-timing checks they carry ---------------------------------------
@pytest.mark.slow
def test_bench_jerk_quick_runs_and_reports_json():
    out = _run_script("bench_jerk.py", "--quick", timeout=300)
    assert out["quick"] is True and out["dtype"] == "float32"
    methods = ("viability", "jerk_zoh", "jerk_semi5", "is_viable_jerk", "jerk_paper")
    assert all(_finite_positive(out[f"{m}_per_s"]) for m in methods), out
    for m in methods[1:]:
        assert math.isclose(out[f"{m}_vs_viability"], out[f"{m}_per_s"] / out["viability_per_s"]), (m, out)
    assert math.isclose(out["jerk_vs_paper"], out["jerk_zoh_per_s"] / out["jerk_paper_per_s"]), out


@pytest.mark.slow
def test_bench_env_quick_runs_and_reports_json():
    out = _run_script("bench_env.py", "--quick", "--repeats", "3", timeout=300)
    assert out["benchmark"] == "bench_env" and out["quick"] is True and out["repeats"] == 3
    assert set(out["throughput"]) == {"planar/64"}
    row = out["throughput"]["planar/64"]
    for k in ("unshielded", "viability", "shield_us", "step_us", "compile_s"):
        assert _finite_positive(row[k]), (k, row)
    assert all(math.isfinite(row[k]) for k in ("overhead_pct/viability", "overhead_cpu_pct/viability")), row
    # random actions: the shielded rollouts never pass a position limit, the unshielded ones do
    assert row["viability_max_violation"] == 0.0 and row["unshielded_max_violation"] > 0.1, row
    a4 = out["alg4"]
    assert a4["arm"] == "planar" and a4["n_samples"] == 20_000
    assert _finite_positive(a4["mjx_s"]) and _finite_positive(a4["c_loop_s"]), a4
    assert a4["max_rel_diff"] < 1e-5, a4  # Alg. 4 over MJX (M, h) = the same reduction over MuJoCo's C
    lower, upper = np.asarray(a4["lower"]), np.asarray(a4["upper"])
    assert lower.shape == upper.shape == (3,) and np.all(lower < 0) and np.all(upper > 0), a4
