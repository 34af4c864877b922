"""MJX adversarial rollouts: the viability shield keeps position and velocity inside, the others do not.

>= 1e5 env-steps per shield on the planar arm (256 envs x 400 steps), >= 2.5e4 on the Panda (64 envs: its MJX
step is ~10x the planar one; marked ``extended``: the campaign, docs/campaign.md, runs it 1e6 per policy class), one jitted lax.scan
per arm, all shields in the same compiled function. Realised-vs-commanded acceleration and the state's distance from
the semi-implicit model used by the bounds are measured in the same runs.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxlimits.envs.arm import make_panda_reach, make_planar_reach
from jaxlimits.envs.adversarial import adversarial_rollout

METHODS = ("none", "clip", "naive", "viability", "jerk")
# The viability and jerk shields get >= 1e5 env-steps per arm each; the baselines, which violate
# within the first episode, fewer (keeps the suite fast on 2 cores).
BATCH = {"none": 16, "clip": 16, "naive": 16, "viability": 256, "jerk": 256}
BATCH_PANDA = dict(BATCH, viability=64, jerk=64)
STEPS = 400
MIN_STEPS = {"planar": 100_000, "panda": 25_000}  # per exact shield


# the Panda's rollouts (~35 s): the campaign runs them at 10^6 per policy class (docs/campaign.md)
@pytest.fixture(scope="module", params=["planar", pytest.param("panda", marks=pytest.mark.extended)])
def results(request):
    env = make_planar_reach() if request.param == "planar" else make_panda_reach()
    out = adversarial_rollout(env, METHODS, BATCH if request.param == "planar" else BATCH_PANDA, STEPS, seed=0)
    print(request.param, json.dumps(out))
    return request.param, env, out


def test_enough_env_steps(results):
    arm, _, out = results
    assert out["viability"]["env_steps"] >= MIN_STEPS[arm]
    assert out["jerk"]["env_steps"] >= MIN_STEPS[arm]


@pytest.mark.parametrize("method", ["viability", "jerk"])
def test_exact_shields_have_zero_position_and_velocity_violations(results, method):
    _, _, out = results
    r = out[method]
    assert r["count/position"] == 0 and r["max/position"] == 0.0, r
    assert r["count/velocity"] == 0 and r["max/velocity"] == 0.0, r
    assert r["count/acceleration"] == 0, r
    if method == "jerk":
        assert r["count/jerk"] == 0, r


@pytest.mark.parametrize("method", ["none", "clip", "naive"])
def test_baselines_violate(results, method):
    _, _, out = results
    assert out[method]["count/position"] > 0, out[method]


def test_commanded_acceleration_is_realised(results):
    """Shielded commands never saturate the motors, and the simulated joint follows the command.

    The tolerances are float32 roundoff of ``M a + h`` solved back through ``M``, not slack in the
    guarantee: the position check above has none.
    """
    _, env, out = results
    for m in ("naive", "viability", "jerk"):
        r = out[m]
        assert r["count/torque"] == 0, (m, r)
        assert r["accel_error"] <= 1e-4 * float(np.max(env.limits.a_max)) * 10, (m, r)
        assert r["model_error"] <= 1e-5, (m, r)
