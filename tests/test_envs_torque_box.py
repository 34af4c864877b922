"""SafetyWrapper(torque_box=True): the per-state torque-feasible box, its conflict rule, and the Panda
with its datasheet accelerations (which its motors cannot always deliver)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxlimits.envs.arm import make_panda_reach
from jaxlimits.envs.adversarial import adversarial_rollout
from jaxlimits.envs.safety import SafetyWrapper


def test_bad_margin_raises():
    from jaxlimits.envs.arm import make_planar_reach

    with pytest.raises(ValueError, match="torque_box_margin"):
        SafetyWrapper(make_planar_reach(torque_samples=0), "viability", torque_box=True, torque_box_margin=1.5)


@pytest.fixture(scope="module")
def datasheet():
    """Panda with the datasheet ``a_max`` (no torque derivation): 32 envs per shield x 300 steps."""
    env = make_panda_reach(torque_samples=0)
    np.testing.assert_array_equal(env.limits.a_max, env.a_max_nominal)
    shields = ["viability", SafetyWrapper(env, "viability", torque_box=True)]
    out = adversarial_rollout(env, shields, 32, 300, seed=0)
    print("panda datasheet a_max", json.dumps(out))
    return out


def test_datasheet_a_max_needs_more_torque_than_the_motors_have(datasheet):
    r = datasheet["viability"]
    assert r["count/torque"] > 0 and r["max/torque"] > 1.0, r


def test_torque_box_flags_every_torque_violation(datasheet):
    """With the box every remaining torque violation happens in a flagged conflict step, and there are fewer.

    No guarantee is claimed: the viability bounds assume full braking at the datasheet ``a_max``
    later, which the motors do not always give (conflicts > 0).
    """
    r, r0 = datasheet["viability+torque_box"], datasheet["viability"]
    assert r["count/torque_unflagged"] == 0, r
    assert r["count/torque_box_conflict"] > 0, r
    assert r["count/torque"] < r0["count/torque"] and r["max/torque"] < r0["max/torque"], (r, r0)
    assert 0.0 < r["min/torque_box_scale"] < 1.0, r
