"""The benchmark script runs: ``benchmarks/bench_bounds.py --quick`` exits 0 and ends in one JSON line."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "bench_bounds.py"


def _positive(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


@pytest.mark.slow
def test_bench_bounds_quick_runs_and_reports_json():
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--quick"], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, f"stdout:\n{proc.stdout[-3000:]}\nstderr:\n{proc.stderr[-3000:]}"
    json_lines = [line for line in proc.stdout.splitlines() if line.startswith("JSON ")]
    assert len(json_lines) == 1, proc.stdout[-3000:]
    assert proc.stdout.rstrip().splitlines()[-1] == json_lines[0]
    result = json.loads(json_lines[0][len("JSON ") :])

    assert result["quick"] is True
    assert result["cpu_count"] >= 1 and result["jax_version"]
    assert set(result["scalar_python"]) == {"viability/zoh", "viability/semi_implicit(5)", "naive/zoh"}
    assert all(_positive(r) for r in result["scalar_python"].values())
    rows = result["results"]
    assert {(r["config"], r["dtype"]) for r in rows} == {
        (c, d) for c in result["scalar_python"] for d in ("float32", "float64")
    }
    for r in rows:
        assert _positive(r["rate"]) and _positive(r["ratio_vs_scalar_python"]), r
        assert r["batch"][1] == 7 and r["samples"] >= 1
    assert _positive(result["best_float32"]["rate"])
    semi = result["semi_implicit5_vs_zoh_float32"]  # the MuJoCo model's headline: rate and ratio, same run
    assert _positive(semi["semi_implicit5_rate"]) and _positive(semi["zoh_rate"])
    assert math.isclose(semi["ratio"], semi["semi_implicit5_rate"] / semi["zoh_rate"])
    assert semi["batch"] == [max(r["batch"][0] for r in rows), 7]  # --quick: its largest batch
    assert all(_positive(r["rate"]) and r["xla_fusions"] >= 1 for r in result["profile_float32_largest_batch"].values())
    flags = result["xla_flag_pass"]
    assert _positive(flags["with_flag"]["rate"]) and _positive(flags["without_flag"]["rate"])
    assert "--xla_cpu_use_fusion_emitters=false" in flags["with_flag"]["xla_flags"]
    assert "xla_cpu_use_fusion_emitters" not in flags["without_flag"]["xla_flags"]
