"""``benchmarks/jerk_training.py``'s statistics on synthetic trajectories of known jerk (NumPy only, no training)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("jerk_training")


def test_known_jerk(bench):
    dt = 0.01
    # one joint, two episodes from rest: jerks [100, 100, 0, -200] and [50, 0, 0, 0] rad/s^3
    acc = np.array([[[1.0], [2.0], [2.0], [0.0]], [[0.5], [0.5], [0.5], [0.5]]])
    s = bench.motion_stats(acc, dt, [150.0])
    jerk = np.array([100, 100, 0, 200, 50, 0, 0, 0], float)
    assert s["steps"] == 8
    assert s["jerk"]["mean"] == pytest.approx(jerk.mean())
    assert s["jerk"]["max"] == pytest.approx(200.0)
    assert s["jerk"]["p95"] == pytest.approx(np.percentile(jerk, 95))
    assert s["jerk"]["p50"] == pytest.approx(np.median(jerk))
    assert s["jerk_at_bound_fraction"] == pytest.approx(1 / 8)  # only the 200 >= 0.99 * 150
    assert s["jerk_over_j_max"]["max"] == pytest.approx(200.0 / 150.0)
    assert s["acc"]["mean"] == pytest.approx(np.abs(acc).mean())
    assert s["acc"]["max"] == 2.0
    assert s["jerk_exceed_steps"] == 1 and s["jerk_exceed_fraction"] == pytest.approx(1 / 8)
    # a start that is not at rest: the first step's jerk is measured from a_prev0
    assert bench.motion_stats(acc, dt, [150.0], a_prev0=2.0)["jerk"]["max"] == pytest.approx(200.0)


def test_exceedance_per_joint_and_at_the_limit(bench):
    dt = np.float32(0.01)
    j_max = np.array([500.0, 600.0], np.float32)
    step = j_max * dt  # 5, 6 rad/s^2 per step: exactly at the limit is not a violation (the env's test)
    ramp = np.cumsum(np.tile(step, (4, 1)), axis=0, dtype=np.float32)  # (4, 2), every step at the limit
    s = bench.motion_stats(ramp[None], float(dt), j_max)
    assert s["jerk_exceed_steps"] == 0 and s["jerk_at_bound_fraction"] == 1.0
    assert s["jerk_over_j_max"]["max"] == pytest.approx(1.0, rel=1e-5)
    over = ramp.copy()
    over[2, 1] += 1.0  # joint 1 jumps by 7 then 5 rad/s^2: step 2 exceeds (7 > 6), step 3 does not (5 < 6)
    s = bench.motion_stats(over[None], float(dt), j_max)
    assert s["jerk_exceed_steps"] == 1
    assert s["per_joint"]["jerk_exceed_fraction"] == [0.0, 0.25]
    assert s["per_joint"]["jerk_max"] == pytest.approx([500.0, 700.0], rel=1e-5)
    with pytest.raises(ValueError, match="episodes, steps, n"):
        bench.motion_stats(ramp, float(dt), j_max)
