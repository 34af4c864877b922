"""TaskSpaceActions: end-effector displacement actions through time-scaled IK, outside the shield (MJX)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.envs.arm import make_panda_reach, make_planar_reach
from jaxlimits.envs.safety import SafetyWrapper
from jaxlimits.envs.task_space import TASK_METRICS, TaskSpaceActions

STEPS = 60


def _rollout(env, action, key):
    @jax.jit
    def run(key):
        s0 = env.reset(key)
        ee_idx = env._idx

        def body(s, _):
            s = env.step(s, action)
            ee = s.pipeline_state.site_xpos[env.base.ee_site][ee_idx]
            return s, (s.metrics, s.pipeline_state.qpos, ee)

        s, out = jax.lax.scan(body, s0, None, length=STEPS)
        return s0.pipeline_state.site_xpos[env.base.ee_site][ee_idx], out

    return jax.tree.map(np.asarray, run(key))


def test_panda_moves_in_3d():
    """The Panda's joints do not all turn about y: its task space is 3-D (its rollout is the planar
    one's code path with k = 3; run ``test_task_space_rollout...`` with ``arm="panda"`` by hand, ~1 min)."""
    env = TaskSpaceActions(SafetyWrapper(make_panda_reach(torque_samples=0), "viability"))
    assert env.action_size == 3 and env.axes == (0, 1, 2)


@pytest.mark.parametrize("arm", ["planar"])
def test_task_space_rollout_moves_along_the_command_inside_the_limits(arm):
    base = make_planar_reach(torque_samples=0) if arm == "planar" else make_panda_reach(torque_samples=0)
    cap = 0.1
    env = TaskSpaceActions(SafetyWrapper(base, "viability"), step_size=0.01, ee_speed_max=cap)
    k = 2 if arm == "planar" else 3
    assert env.action_size == k and env.axes == ((0, 2) if arm == "planar" else (0, 1, 2))
    direction = np.zeros(k, np.float32)
    direction[0] = 1.0 / np.sqrt(2.0)
    direction[-1] = -1.0 / np.sqrt(2.0)
    ee0, (metrics, qs, ees) = _rollout(env, jnp.asarray(direction), jax.random.PRNGKey(3))
    for key in TASK_METRICS:
        assert np.all(np.isfinite(metrics[key]))
    # the shield underneath: no joint limit is crossed, whatever the IK layer asked
    lim = base.limits
    assert np.all(metrics["violation/position"] == 0.0) and np.all(metrics["violation/velocity"] == 0.0)
    assert np.all((qs >= lim.q_min - 1e-6) & (qs <= lim.q_max + 1e-6))
    # the time scaling: T = ||dr|| / cap (the cap decides here), never below the control period
    assert np.all(metrics["task/T"] >= env.dt * (1 - 1e-6))
    np.testing.assert_allclose(metrics["task/T"], 0.01 / cap, rtol=1e-3)
    assert np.all(metrics["task/unreached"] == 0.0)
    # once the deadbeat velocity tracking has caught up (the shield clips the first steps'
    # accelerations joint by joint), the end effector moves along the command at the capped speed
    move = ees[-1] - ees[STEPS // 3]
    assert move @ direction / np.linalg.norm(move) > 0.98
    speed = np.linalg.norm(move) / ((STEPS - 1 - STEPS // 3) * env.dt)
    assert 0.8 * cap < speed < 1.05 * cap
    assert np.max(metrics["task/speed"]) < 1.2 * cap


def test_bad_configuration_raises():
    base = make_planar_reach(torque_samples=0)
    with pytest.raises(ValueError, match="step_size"):
        TaskSpaceActions(SafetyWrapper(base), step_size=0.0)
    with pytest.raises(ValueError, match="axes"):
        TaskSpaceActions(SafetyWrapper(base), axes=(0, 0))
    with pytest.raises(ValueError, match="ee_speed_max"):
        TaskSpaceActions(SafetyWrapper(base), ee_speed_max=-1.0)
    with pytest.raises(TypeError, match="ArmReach"):
        TaskSpaceActions(object())
