"""``benchmarks/apg_vs_ppo.py``'s pure-Python parts on synthetic metrics rows (no training, no JAX program)."""

from __future__ import annotations

import json

import pytest
from conftest import load_benchmark

from jaxlimits.training import config, plots


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("apg_vs_ppo")


def _apg_rows():
    """Rows as ``brax_apg`` writes them: step 0 (eval only), then per epoch Brax's cumulative ``training/walltime``."""
    return [
        {"step": 0, "wall_s": 20.0, "eval/episode_reward": -150.0},
        # epochs 1 and 2 compile the update (90 s and 40 s), the evaluator compiles again at row 1 (15 s)
        {"step": 8192, "wall_s": 135.0, "eval/episode_reward": -140.0, "training/walltime": 100.0},
        {"step": 16384, "wall_s": 180.0, "eval/episode_reward": -130.0, "training/walltime": 140.0},
        # steady: 10 s epochs (819.2 env-steps/s) + 5 s evaluations
        {"step": 24576, "wall_s": 195.0, "eval/episode_reward": -120.0, "training/walltime": 150.0},
        {"step": 32768, "wall_s": 210.0, "eval/episode_reward": -110.0, "training/walltime": 160.0},
    ]


def test_calibration_and_budget(bench):
    cal = bench.calibration_from_rows(_apg_rows())
    # fixed: 180 s to the third row less two steady intervals of 15 s
    assert cal == pytest.approx({"fixed_s": 150.0, "eval_s": 5.0, "env_steps_per_s": 819.2})
    cfg = config.load("planar_reach_apg")  # 128 envs x 32 steps, 10 epochs
    steps = bench.apg_timesteps_for_budget(cal, 900.0, cfg)
    # (900 - 150 - 10 * 5) s * 819.2 steps/s = 573,440 steps = 140 updates -> 14 per epoch
    assert steps == 140 * 4096
    assert bench.apg_timesteps_for_budget(cal, 10.0, cfg) == 10 * 4096  # at least one update per epoch
    with pytest.raises(ValueError, match="4 metrics rows"):
        bench.calibration_from_rows(_apg_rows()[:3])


def test_curves_and_table_from_metrics_files(bench, tmp_path):
    ppo_rows = [
        {"step": 0, "wall_s": 10.0, "eval/return_mean": -200.0, "eval/success_rate": 0.0},
        {"step": 100, "wall_s": 30.5, "eval/return_mean": 50.0, "eval/success_rate": 0.5},
    ]
    for name, rows in (("ppo", ppo_rows), ("apg", _apg_rows())):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    c = bench.curve(plots.read_rows(tmp_path / "ppo"))
    assert c == {"wall_s": [10.0, 30.5], "step": [0, 100], "return": [-200.0, 50.0], "success": [0.0, 0.5]}
    c = bench.curve(plots.read_rows(tmp_path / "apg"))
    assert c["wall_s"] == [20.0, 135.0, 180.0, 195.0, 210.0] and c["return"] == [-150.0, -140.0, -130.0, -120.0, -110.0]
    assert c["success"] == [None] * 5  # Brax's APG evaluator logs no success
    zero = {"violations/position": 0, "violations/velocity": 0}
    results = {
        "runs": {
            "apg_exact": {
                "gradient": "exact",
                "learning_env_steps": 16384,
                "training_wall_s": 140.0,
                "training": zero,
                "evaluation": {"success_rate": 0.25, "return_mean": -12.345, **zero},
            }
        }
    }
    table = bench.format_table(results).splitlines()
    assert table[0] == bench.HEAD and len(table) == 3
    assert table[2] == "| apg_exact | exact | 16,384 | 140 | 117 | 0.250 | -12.35 | 0 / 0 | 0 / 0 |"
