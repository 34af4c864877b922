"""Stiff position servos on light links under MJX's float32: the shield keeps clear of the ctrl rounding.

Kinova Gen3 (Menagerie's servos, no armature, four unlimited joints that ride ``v_max``): rounding the servo's
``ctrl`` (the position plus a small offset) to float32 moves its force by ``kp ulp(q)``, and the acceleration
by up to ~4e-3 rad/s^2 through the light wrists. Riding the velocity limit, that alone broke ``v_max`` by
~5e-5 rad/s in most steps. ``Robot.ctrl_quantum`` bounds the error; the Brax wrapper's decision tightens the
limits by the velocity it gives over a control step (``SafeAcceleration(realisation_margin=True)``).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.adversarial import inside_reset, shield_rollout
from jaxlimits.envs.joint_shield import QUANTUM_SAFETY, SafeAcceleration
from jaxlimits.envs.reach import make_gen3_reach, make_servo_panda_reach

BATCH, STEPS = 16, 60


def _shield(margin: bool = True):
    env = JointLimitShield(make_gen3_reach(), method="viability")
    if not margin:  # the decision as it was: limits not tightened
        env.decide = SafeAcceleration(env.robot, env.n_frames, "viability")
    return env


def test_the_quantum_is_the_servos_rounding_through_the_links_inertia():
    """Gen3's four unlimited joints are read (no position limit, ctrl within ±2π); the quantum is larger on the
    light wrist than on the servo Panda (armature 0.1, joint damping 2-40) and tiny against ``a_max``; the
    margin it gives is a small fraction of ``v_max``."""
    gen3 = _shield()
    r = gen3.robot
    assert list(r.limited) == [False, True, False, True, False, True, False]
    assert np.all(r.ctrl_quantum > 0) and np.all(r.ctrl_quantum < 1e-3 * r.limits.a_max)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        panda = JointLimitShield(make_servo_panda_reach(), method="viability").robot
    assert np.max(r.ctrl_quantum) > 2 * np.max(panda.ctrl_quantum)
    m_v = r.limits.v_max - gen3.decide.limits.v_max
    expected = QUANTUM_SAFETY * gen3.n_frames * r.timestep * r.ctrl_quantum
    np.testing.assert_allclose(m_v, expected, rtol=1e-9)  # v_max - (v_max - m): a few ulps of v_max
    assert np.all(m_v < 1e-3 * r.limits.v_max)
    # positions tightened by the margin's travel over a control step (limited joints; unlimited ones have none)
    np.testing.assert_allclose(
        (gen3.decide.limits.q_min - r.limits.q_min)[r.limited], (m_v * gen3.decide.dt)[r.limited]
    )


@pytest.mark.parametrize("margin", [True, False], ids=["margin", "no_margin"])
def test_gen3_under_adversarial_policies(margin):
    """Every substep measured: with the margin 0 position and velocity violations and the realisation error within
    what the margin covers; without it (the decision riding the model's own ``v_max``) the float32 rounding
    breaks the velocity limit, so the test can fail."""
    env = _shield(margin)
    r = shield_rollout(env, BATCH, STEPS, reset=inside_reset(env))
    assert r["env_steps"] == BATCH * STEPS and r["count/disturbance"] == 0 and r["count/saturated"] == 0
    err = float(r["undisturbed/max/accel_error"])
    assert 0 < err <= QUANTUM_SAFETY * np.max(env.robot.ctrl_quantum), err
    if margin:
        assert r["count/position"] == 0 and r["count/velocity"] == 0, r
    else:
        assert r["count/velocity"] > BATCH * STEPS // 10, r
        assert float(r["max/velocity"]) < 1e-3  # a rounding's worth, not a failure of the bounds


def test_a_margin_over_a_percent_of_v_max_is_refused_by_joint_name():
    """A servo so stiff against its link that its rounding alone moves the velocity by >= 1 % of ``v_max`` per step."""
    robot = _shield().robot
    stiff = dataclasses.replace(robot, ctrl_quantum=robot.ctrl_quantum * np.where(np.arange(robot.n) == 4, 1e3, 1.0))
    with pytest.raises(ValueError, match=r"joints \{'joint_5': .*1 % of v_max"):
        SafeAcceleration(stiff, 5, "viability", realisation_margin=True)
    SafeAcceleration(robot, 5, "viability", realisation_margin=True)  # the shipped model is accepted
