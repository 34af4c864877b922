"""The wall-strike task over any robot (``envs/strike.py``) under the one shield: the planar arm driven into its wall
at 1.5 m/s, the impact cap enforced, its strikes measured by the shield, the joints' limits kept while it presses the
wall (where the motors have the torque); bad input is an eager error."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from jaxlimits.envs import JointLimitShield
from jaxlimits.envs.strike import Strike, make_planar_robot_wall, strike_point
from jaxlimits.envs.wall_strike import PLANAR_HOME


def _toward_wall(task, shielded, speed: float, gain: float = 20.0):
    """The action (``[-1, 1]``, joint accelerations over the MJCF's ``a_max``) driving the ball along the wall's
    normal at ``speed`` [m/s] (resolved rate, damped pseudo-inverse, the null space damped), scaled into the box."""
    a_max = jnp.asarray(shielded.robot.limits.a_max, jnp.float32)
    nrm = jnp.asarray(task.normal, jnp.float32)

    def action(ps):
        jacp, _ = mjx.jac(task.sys, ps, ps.site_xpos[task._site], task._body)
        J = jacp.T
        JJt = J @ J.T + 1e-4 * jnp.eye(3)
        pinv = J.T @ jnp.linalg.inv(JJt)
        a = gain * (pinv @ (speed * nrm - J @ ps.qvel)) - gain * ((jnp.eye(J.shape[1]) - pinv @ J) @ ps.qvel)
        a = a / a_max
        return a / jnp.maximum(1.0, jnp.max(jnp.abs(a)))  # scaled, not clipped: the direction kept

    return action


@pytest.fixture(scope="module")
def pressed():
    """16 planar arms driven at their walls at 1.5 m/s for an episode (200 steps) under the one shield and its cap:
    ``(steps, 16)`` arrays of the shield's record."""
    task = make_planar_robot_wall()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # the torque-derived a_max's quantile notice
        env = JointLimitShield(task, impact=strike_point(task))
    assert env.violations == ("position", "velocity", "torque", "jerk", "impact")
    batch, steps = 16, 200  # an episode: the cap brings the ball in slowly (up to 25 cm)
    action = _toward_wall(task, env, 1.5)

    @jax.jit
    def run(key):
        def body(s, _):
            s = jax.vmap(env.step)(s, jax.vmap(action)(s.pipeline_state))
            m, v = s.metrics, s.info["violation"]
            return s, {
                "strike": m["shield/strike"],
                "ratio": m["shield/strike_ratio"],
                "speed": m["shield/strike_speed"],
                "impact": v["impact"],
                "position": v["position"],
                "velocity": v["velocity"],
                "success": m["success"],
                "cap": m["shield/impact_cap"],
                "touched": s.info["shield_strike"]["struck"],  # a contact in some substep so far
                "saturated": m["shield/saturated"],
            }

        return jax.lax.scan(body, jax.vmap(task.reset)(jax.random.split(key, batch)), None, length=steps)[1]

    return {k: np.asarray(x) for k, x in run(jax.random.PRNGKey(0)).items()}


def test_the_cap_keeps_every_strike_of_the_planar_arm_within_its_bound(pressed):
    """Every arm strikes its wall (the task's success); the shield's cap brings the ball in at a fraction of the
    1.5 m/s the command asks, every strike is measured within the impulsive-torque bound (none counted), and no joint
    leaves its position or velocity limit before its ball first touches the wall (the guarantee's scope)."""
    r = pressed
    assert np.all(r["success"][-1] == 1.0), "every arm reaches its wall"
    assert np.all(r["strike"].sum(axis=0) >= 1) and np.all(r["ratio"][r["strike"] > 0] > 0)
    assert np.max(r["ratio"]) <= 1.0 and np.all(r["impact"] == 0), np.max(r["ratio"])
    assert np.max(r["speed"]) < 0.5 * 1.5, "the cap slowed the strikes the command asked 1.5 m/s for"
    before = np.concatenate([np.zeros((1, r["touched"].shape[1])), r["touched"][:-1]]) == 0  # no contact yet
    assert before.sum() > 500  # ~50 steps of approach per arm
    assert np.max(r["position"][before]) <= 0 and np.max(r["velocity"][before]) <= 0
    assert np.all(np.isfinite(r["cap"])) and np.max(r["cap"]) > 0


def test_pressing_the_wall_breaks_no_velocity_limit(pressed):
    """Pressed on the frictionless wall for the rest of the episode: no joint leaves its velocity limit, and a position
    limit only after the actuators were counted short of the torque that kept the contact's push inside the bounds
    (``shield/saturated``), by at most 1e-3 rad. Before the contact correction was boxed by the torque the actuators
    have (``contact_correction(torque_box=)``), its unboxed torque pulled the ball off the wall and the joints took
    it: 26 velocity-violating steps (up to 0.52 rad/s over) and 180 position-violating ones (up to 0.074 rad)."""
    r = pressed
    assert np.max(r["velocity"]) <= 0
    short_before = np.cumsum(r["saturated"], axis=0) > 0  # a saturation counted in this episode so far
    violating = r["position"] > 0
    assert np.all(short_before[violating]), np.argwhere(violating & ~short_before)
    assert np.max(r["position"]) <= 1e-3, np.max(r["position"])


def test_bad_strike_input_is_an_eager_error_naming_it():
    from jaxlimits.envs.reach import ASSETS

    xml = ASSETS / "planar3.xml"
    with pytest.raises(ValueError, match="home must be 3"):
        Strike(xml, home=[0.0, 0.0])
    with pytest.raises(ValueError, match="normal"):
        Strike(xml, PLANAR_HOME, normal=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="gap_low <= gap_high"):
        Strike(xml, PLANAR_HOME, gap_low=0.2, gap_high=0.1)
    with pytest.raises(ValueError, match="impulse_limit"):
        Strike(xml, PLANAR_HOME, impulse_limit=float("nan"))
