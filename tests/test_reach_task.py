"""The reach task over any robot (``envs/reach.py``) and its training config on the position-servo Panda:
the servo-offset action, Isaac Lab's start/target distribution, the IK observation, the reward, the
metric names the trainers read (``envs/violation_metrics.py``), bad input, and PPO end to end on a tiny
budget through the shield (0 violations, every env-step counted)."""

from __future__ import annotations

import functools
import json

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest


from jaxlimits.envs.arm import ASSETS, PANDA_FRONT_BOX, PRECISION_SCALE, VIOLATION_KEYS, State, damped_ls_step
from jaxlimits.envs.reach import Reach, make_planar_robot_reach, make_servo_panda_front_reach, servo_offset_scale
from jaxlimits.envs.violation_metrics import _with_metrics
from jaxlimits.training import config

PANDA_SERVO = ASSETS / "panda_servo.xml"


@pytest.fixture(scope="module")
def front():
    return make_servo_panda_front_reach(precision_reward=1.0)


@pytest.fixture(scope="module")
def resets(front):
    return jax.jit(jax.vmap(front.reset))(jax.random.split(jax.random.PRNGKey(3), 256))


@pytest.mark.parametrize("action", ["servo_offset", "ctrl", "acceleration"])
def test_reach_and_its_shield_trace_in_float64(action):
    """Under ``jax_enable_x64`` the reset's state has the physics' dtype (float64) and keeps it through a step, bare
    and shielded, a float32 action given. Before, reset gave float32 positions that MJX's step made float64, and
    ``ctrl`` actions a float32 ``ctrl``: Brax's substep scan (bare) and the shield's (its decision's ``cond``, its
    carry's ``ctrl``) raised a carry-type error."""
    from jaxlimits.envs import JointLimitShield

    with jax.enable_x64(True):
        if action == "acceleration":  # the planar arm: the servo Panda ships no jaxlimits_a_max
            make = make_planar_robot_reach
        else:
            make = functools.partial(make_servo_panda_front_reach, action=action)
        for env in (make(), JointLimitShield(make())):
            s0 = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
            s1 = jax.eval_shape(env.step, s0, jax.ShapeDtypeStruct((env.action_size,), jnp.float32))
            assert s0.pipeline_state.qpos.dtype == s0.pipeline_state.qvel.dtype == jnp.float64
            assert jax.tree.structure(s0) == jax.tree.structure(s1)
            assert all(jax.tree.leaves(jax.tree.map(lambda a, b: a.dtype == b.dtype, s0, s1)))


def test_servo_offset_scale_is_the_force_range_over_kp():
    mjm = mujoco.MjModel.from_xml_path(str(PANDA_SERVO))
    np.testing.assert_allclose(servo_offset_scale(mjm), [0.1, 0.1, 100 / 750, 100 / 750, 0.04, 0.04, 0.04])


def test_servo_offset_at_rest_asks_the_servos_action_times_their_force(front, resets):
    """``ctrl = q + action * forcerange / kp``: at rest the servo's force ``kp (ctrl - q)`` is
    ``action * forcerange`` (its whole force at |action| = 1, the same on every joint)."""
    mjm = front.sys.mj_model
    kp, force = mjm.actuator_gainprm[:, 0], mjm.actuator_forcerange[:, 1]
    ps = jax.tree.map(lambda x: x[0], resets.pipeline_state)
    for action in (np.ones(7), -np.ones(7), np.linspace(-1, 1, 7)):
        ctrl = np.asarray(front.ctrl(ps, jnp.asarray(action, jnp.float32)), np.float64)
        np.testing.assert_allclose(kp * (ctrl - np.asarray(ps.qpos)), action * force, rtol=1e-5, atol=1e-3)


def test_front_reach_draws_isaac_labs_starts_and_targets(front, resets):
    home = front.sys.mj_model.key_qpos[0]
    q = np.asarray(resets.pipeline_state.qpos)
    target = np.asarray(resets.info["target"])
    lo, hi = np.asarray(front._q_lo), np.asarray(front._q_hi)
    assert np.all(q >= lo - 1e-6) and np.all(q <= hi + 1e-6)
    ratio = q[:, home != 0] / home[home != 0]
    clipped = np.isclose(q[:, home != 0], lo[home != 0]) | np.isclose(q[:, home != 0], hi[home != 0])
    assert np.all((ratio >= 0.5 - 1e-6) & (ratio <= 1.5 + 1e-6) | clipped)
    assert np.all(q[:, home == 0] == 0) and ratio.std() > 0.2  # scaled, not the keyframe itself
    box = np.asarray(PANDA_FRONT_BOX)
    assert np.all(target >= box[0]) and np.all(target <= box[1])
    assert np.all(np.ptp(target, axis=0) > 0.5 * (box[1] - box[0]))
    assert np.all(np.asarray(resets.pipeline_state.qvel) == 0)


def test_ik_observation_and_reward(front, resets):
    """The last ``n`` observation entries are the damped least-squares step with the Jacobian of the ``ee``
    site's forward kinematics (autodiff, independent of ``mjx.jac``); the reward's precision term."""
    i = 5
    ps = jax.tree.map(lambda x: x[i], resets.pipeline_state)
    target = resets.info["target"][i]
    J = jax.jacfwd(front._ee)(ps.qpos)
    ee = front._ee(ps.qpos)
    want = damped_ls_step(J, target - ee)
    obs = resets.obs[i]
    assert obs.shape == (4 * 7 + 6,) == (front.observation_size,)
    np.testing.assert_allclose(obs[-7:], want, rtol=2e-4, atol=2e-5)
    np.testing.assert_allclose(obs[-10:-7], target - ee, atol=1e-6)
    state = jax.tree.map(lambda x: x[i], resets)
    nxt = jax.jit(front.step)(state, jnp.zeros(7, jnp.float32))  # unshielded: the task alone
    d = float(nxt.metrics["distance"])
    np.testing.assert_allclose(float(nxt.reward), -d + 1.0 * (1 - np.tanh(d / PRECISION_SCALE)), rtol=1e-5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"action": "torque"}, "action must be one of"),
        ({"start": "anywhere"}, "start must be one of"),
        ({"target": "far"}, "target must be one of"),
        ({"target": "box"}, "target_box"),
        ({"target": "box", "target_box": ((0, 0, 0), (1, -1, 1))}, "target_box"),
        ({"precision_reward": -1.0}, "precision_reward"),
        ({"home_scale": (1.5, 0.5), "start": "home"}, "home_scale"),
    ],
)
def test_bad_reach_options_raise_naming_them(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Reach(PANDA_SERVO, **kwargs)


def test_servo_offset_on_motors_names_the_actuator():
    geared = mujoco.MjModel.from_xml_path(str(PANDA_SERVO))
    geared.actuator_gear[2, 0] = 2.0  # its target would be 2 q, not q
    with pytest.raises(ValueError, match="position servos; actuator 'actuator3'"):
        servo_offset_scale(geared)
    with pytest.raises(ValueError, match="position servos; actuator 'm1'"):
        Reach(ASSETS / "planar3.xml", action="servo_offset")
    with pytest.raises(ValueError, match="keyframe named 'home'"):
        Reach(ASSETS / "planar3.xml", start="home")


def test_violation_metrics_rename_the_shields_record():
    zero = jnp.zeros((), jnp.float32)
    shield = {
        "shield/intervention": 3.0,
        "shield/nonviable": 1.0,
        "shield/nonfinite": 1.0,
        "shield/torque_conflict": 0.0,
        "shield/disturbance": 0.5,
    }
    state = State(
        pipeline_state=None,
        obs=jnp.zeros(2),
        reward=zero,
        done=zero,
        metrics={k: jnp.float32(v) for k, v in shield.items()},
        info={"violation": {"position": jnp.float32(0.0), "velocity": jnp.float32(0.25), "torque": jnp.float32(2.0)}},
    )
    m = _with_metrics(state).metrics
    assert {f"count/{k}" for k in VIOLATION_KEYS} <= set(m) and {f"violation/{k}" for k in VIOLATION_KEYS} <= set(m)
    assert [float(m[f"count/{k}"]) for k in ("position", "velocity", "torque", "jerk")] == [0, 1, 1, 0]
    assert float(m["violation/velocity"]) == 0.25 and float(m["violation/torque"]) == 2.0
    assert float(m["intervention"]) == 3.0 and float(m["viable"]) == 0.0 and float(m["nonfinite_action"]) == 1.0
    assert float(m["torque_box_conflict"]) == 0.0
    assert float(m["disturbance"]) == 0.5  # a contact pushed a shielded joint: the evaluator's disturbed steps


@pytest.mark.parametrize(
    "env, bad, field",
    [
        ("servo_panda_front_reach", {"action_mode": "velocity"}, "action_mode"),
        ("servo_panda_front_reach", {"shield": "clip"}, "shield"),
        ("servo_panda_front_reach", {"algo": "apg"}, "algo"),
        ("planar_reach", {"action_mode": "servo_offset"}, "action_mode"),
    ],
)
def test_servo_config_fields_are_checked_eagerly(env, bad, field):
    d = config.load("tiny").to_dict()
    d.update(env=env, action_mode="servo_offset" if env.startswith("servo") else "velocity")
    d.update(bad)
    with pytest.raises(ValueError, match=f"'{field}' must be one of .* for env '{env}'"):
        config.from_dict(d)


def test_servo_panda_front_reach_trains_end_to_end_on_a_tiny_budget(tmp_path):
    """PPO on the shielded servo Panda (the shipped config's env, action and observation; tiny sizes):
    every training and evaluation env-step counted, 0 position / velocity / torque violations."""
    from jaxlimits.training import brax_ppo, experiment

    shipped = config.load("servo_panda_front_reach_ppo")
    assert (shipped.env, shipped.action_mode, shipped.ik_observation) == (
        "servo_panda_front_reach",
        "servo_offset",
        True,
    )
    d = config.load("tiny").to_dict()
    d.update(env=shipped.env, action_mode=shipped.action_mode)  # tiny's eval_episodes: the in-training evaluator's
    cfg = config.from_dict(d)
    res = experiment.train_and_evaluate(cfg, tmp_path / "run", show_progress=False)
    tr, ev = res["training"], res["evaluation"]
    assert tr["env_steps"] == brax_ppo.total_env_steps(cfg)
    assert ev["episodes"] == cfg.eval_episodes
    for k in ("position", "velocity", "torque"):
        assert tr[f"violations/{k}"] == 0 and ev[f"violations/{k}"] == 0, (k, tr, ev)
    assert 0.0 <= ev["success_rate"] <= 1.0 and np.isfinite(ev["final_distance_mean"])
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["env"] == "servo_panda_front_reach"
