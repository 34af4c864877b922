"""``benchmarks/pusher_contacts.py``'s contact speed: the approach speed along the normal, signed toward the other geom."""

from __future__ import annotations

import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
from pusher_contacts import arm_contacts  # noqa: E402

BALL = """
<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <body name="ball" pos="0 0 0.1"><freejoint/><geom name="ball" type="sphere" size="0.1"/></body>
  </worldbody>
</mujoco>
"""


@pytest.mark.parametrize("vz", [-0.7, 0.3])
def test_the_approach_speed_is_the_velocity_along_the_normal_toward_the_other_geom(vz):
    m = mujoco.MjModel.from_xml_string(BALL)
    d = mujoco.MjData(m)
    d.qpos[2] = 0.099  # 1 mm into the floor: one contact
    mujoco.mj_forward(m, d)
    assert d.ncon == 1
    ball = m.body("ball").id
    qvel = np.zeros(m.nv)
    qvel[:3] = (0.2, -0.1, vz)  # tangential components do not approach
    # the ball is geom2 of the floor-ball contact: the normal is flipped to point from it to the floor
    ((pair, speed),) = arm_contacts(m, d, {ball}, qvel).items()
    assert pair == (m.geom("floor").id, m.geom("ball").id)
    assert speed == pytest.approx(-vz, abs=1e-12)
    assert arm_contacts(m, d, {m.body("world").id}, qvel)[pair] == pytest.approx(0.0, abs=1e-12)  # the floor is still
    assert arm_contacts(m, d, set(), qvel) == {}
