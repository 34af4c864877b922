"""Gymnasium front: ``gymnasium.Env`` and ``gymnasium.vector.VectorEnv`` over the jitted MJX envs.

Numpy in, numpy out; the physics and the shield run in one jitted, vmapped function per batch size
(the single env is the vector env's code with one env). Registered ids (``register_envs`` runs on
import of this module):

    gymnasium.make("jaxlimits/PandaReach-v0", shield="viability")
    gymnasium.make("jaxlimits/PlanarReach-v0", shield="none")

``shield`` is one of ``SafetyWrapper``'s methods; ``torque_box=True`` adds its per-state torque box.
``action_mode`` (``"acceleration"`` default, ``"velocity"``, ``"task_space"``: ``jaxlimits.envs.actions``),
``ik_observation`` and ``precision_reward`` (``ArmReach``'s options) choose the task as in the Brax
configs (``docs/training.md``).
The reach task has no terminal state (``terminated`` is always False); episodes end by truncation
after ``max_episode_steps`` (``TimeLimit`` from the registration for the single env; the vector env
truncates itself and resets in the same step, ``autoreset_mode = SAME_STEP``, as Gymnasium's
``SyncVectorEnv`` does: for the envs that were reset, ``info["final_obs"]`` (object array, ``None``
elsewhere) holds the last observation and ``info["final_info"]`` the last step's info, masked by
``info["_final_obs"]``/``info["_final_info"]``, while the top-level ``info`` entries of those envs
describe the fresh state, as a reset's do). ``gymnasium.make_vec(id, num_envs, shield=...)`` builds
an ``ArmVectorEnv`` (the registered ``vector_entry_point``); ``vectorization_mode="sync"`` also
works (a ``SyncVectorEnv`` of ``ArmEnv``s, each stepped on its own).

Every step's ``info`` carries ``info["violation"]``: ``{"position", "velocity", "acceleration",
"jerk", "torque"}`` -> the largest violation magnitude over the joints (and substeps) in this step,
0.0 when none, and ``info["qpos"]``, ``info["qvel"]`` (the arm's joints after the step), plus
``info["intervention"]`` (``max |a_safe - a_des|``) and ``info["accel_error"]``. A violation in the
last step of a vector env's episode is in ``info["final_info"]["violation"]``.

Worker processes: JAX cannot run in a process forked after JAX started, so these envs refuse to be built there
with an error naming the start methods that work (``fork_guard``): Gymnasium's ``AsyncVectorEnv`` needs
``context="forkserver"`` (or ``"spawn"``); Stable-Baselines3's ``SubprocVecEnv`` works as it is.

``render_mode="rgb_array"`` renders with MuJoCo's ``Renderer``; headless it needs
``MUJOCO_GL=egl`` (set by default by ``jaxlimits.envs`` when unset) and libEGL; ``osmesa`` needs
the system package ``libosmesa6``.
"""

from __future__ import annotations

import functools

import gymnasium
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from jaxlimits.envs.actions import with_action_mode
from jaxlimits.envs.arm import VIOLATION_KEYS, make_panda_reach, make_planar_reach
from jaxlimits.envs.fork_guard import check_not_forked_from_jax
from jaxlimits.envs.safety import SafetyWrapper

ARMS = {"planar": make_planar_reach, "panda": make_panda_reach}


@functools.cache
def _arm(name: str, ik_observation: bool = False, precision_reward: float = 0.0):
    return ARMS[name](ik_observation=ik_observation, precision_reward=precision_reward)


@functools.cache
def _batched(
    arm: str,
    shield: str,
    torque_box: bool = False,
    action_mode: str = "acceleration",
    ik_observation: bool = False,
    precision_reward: float = 0.0,
):
    """Jitted ``reset(keys)`` and ``step(states, actions)`` for a batch of shielded envs, the
    ``SafetyWrapper`` and the outer env (with the action mode) (cached)."""
    shielded = SafetyWrapper(_arm(arm, bool(ik_observation), float(precision_reward)), shield, torque_box=torque_box)
    outer = with_action_mode(shielded, action_mode)
    return jax.jit(jax.vmap(outer.reset)), jax.jit(jax.vmap(outer.step)), shielded, outer


def _infos(states) -> dict:
    m = jax.device_get(states.metrics)
    d = states.pipeline_state
    return {
        "violation": {k: np.asarray(m[f"violation/{k}"], np.float64) for k in VIOLATION_KEYS},
        "qpos": np.asarray(d.qpos, np.float64),
        "qvel": np.asarray(d.qvel, np.float64),
        "intervention": np.asarray(m["intervention"], np.float64),
        "accel_error": np.asarray(m["accel_error"], np.float64),
    }


class _Core:
    """Shared state handling for ``ArmEnv`` and ``ArmVectorEnv``."""

    def _setup(
        self,
        arm: str,
        shield: str,
        num_envs: int,
        render_mode,
        width: int,
        height: int,
        torque_box: bool = False,
        action_mode: str = "acceleration",
        ik_observation: bool = False,
        precision_reward: float = 0.0,
    ):
        check_not_forked_from_jax(type(self).__name__)  # before any JAX call (fork_guard)
        if arm not in ARMS:
            raise ValueError(f"arm must be one of {tuple(ARMS)}, got {arm!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self._reset_fn, self._step_fn, self._wrapped, outer = _batched(
            arm, shield, bool(torque_box), action_mode, bool(ik_observation), float(precision_reward)
        )
        env = self._wrapped.env
        self.arm, self.shield = arm, shield
        self._B = num_envs
        self._states = None
        self._key = jax.random.PRNGKey(0)
        self._render_size = (height, width)
        self._renderer = None
        self._mjd = None
        # [cos q, sin q, qvel, ee, target - ee (, ik step)]; finite bounds wide enough for unshielded runaways
        n = env.n
        parts = [np.ones(2 * n), np.full(n, 1e4), np.full(6, 10.0)] + ([np.full(n, 1e3)] if env.ik_observation else [])
        high = np.concatenate(parts).astype(np.float32)
        obs_space = spaces.Box(-high, high, (env.observation_size,), np.float32)
        self._n = outer.action_size
        act_space = spaces.Box(-1.0, 1.0, (outer.action_size,), np.float32)
        return env, obs_space, act_space

    def _do_reset(self, seed):
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        self._key, sub = jax.random.split(self._key)
        return self._reset_fn(jax.random.split(sub, self._B))

    def _frame(self, i: int):
        env = self._wrapped.env
        if self._renderer is None:
            self._mjm = mujoco.MjModel.from_xml_path(str(env.xml_path))
            self._mjd = mujoco.MjData(self._mjm)
            self._renderer = mujoco.Renderer(self._mjm, *self._render_size)
            self._target_site = mujoco.mj_name2id(self._mjm, mujoco.mjtObj.mjOBJ_SITE, "target")
        s = self._states
        self._mjd.qpos[:] = np.asarray(s.pipeline_state.qpos[i])
        self._mjm.site_pos[self._target_site] = np.asarray(s.info["target"][i])
        mujoco.mj_forward(self._mjm, self._mjd)
        self._renderer.update_scene(self._mjd)
        return self._renderer.render().copy()

    def _close_renderer(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


class ArmEnv(_Core, gymnasium.Env):
    """One MJX arm reach env behind the Gymnasium API (observations float32, actions in [-1, 1]^n)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 100}

    def __init__(
        self,
        arm: str = "planar",
        shield: str = "viability",
        render_mode=None,
        width: int = 240,
        height: int = 240,
        torque_box: bool = False,
        action_mode: str = "acceleration",
        ik_observation: bool = False,
        precision_reward: float = 0.0,
    ):
        env, self.observation_space, self.action_space = self._setup(
            arm, shield, 1, render_mode, width, height, torque_box, action_mode, ik_observation, precision_reward
        )
        self.render_mode = render_mode
        self.metadata = dict(self.metadata, render_fps=int(round(1.0 / env.dt)))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self._states = self._do_reset(seed)
        info = {k: (v if k != "violation" else {kk: 0.0 for kk in v}) for k, v in _infos(self._states).items()}
        info = {k: (v[0] if isinstance(v, np.ndarray) else v) for k, v in info.items()}
        return np.asarray(self._states.obs[0], np.float32), info

    def step(self, action):
        a = jnp.asarray(np.asarray(action, np.float32).reshape(1, self._n))
        self._states = self._step_fn(self._states, a)
        info = _infos(self._states)
        info = {
            "violation": {k: float(v[0]) for k, v in info["violation"].items()},
            **{k: v[0] for k, v in info.items() if k != "violation"},
        }
        return (np.asarray(self._states.obs[0], np.float32), float(self._states.reward[0]), False, False, info)

    def render(self):
        if self.render_mode != "rgb_array" or self._states is None:
            return None
        return self._frame(0)

    def close(self):
        self._close_renderer()


class ArmVectorEnv(_Core, VectorEnv):
    """``num_envs`` MJX arm reach envs in one jitted, vmapped step (autoreset in the same step)."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        num_envs: int,
        arm: str = "planar",
        shield: str = "viability",
        max_episode_steps: int = 500,
        render_mode=None,
        width: int = 240,
        height: int = 240,
        torque_box: bool = False,
        action_mode: str = "acceleration",
        ik_observation: bool = False,
        precision_reward: float = 0.0,
    ):
        env, obs1, act1 = self._setup(
            arm, shield, num_envs, render_mode, width, height, torque_box, action_mode, ik_observation, precision_reward
        )
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = obs1, act1
        self.observation_space = gymnasium.vector.utils.batch_space(obs1, num_envs)
        self.action_space = gymnasium.vector.utils.batch_space(act1, num_envs)
        self.render_mode = render_mode
        self.max_episode_steps = max_episode_steps
        self._t = np.zeros(num_envs, np.int64)

    def _reset_info(self, states):
        info = _infos(states)
        info["violation"] = {k: np.zeros(self.num_envs) for k in VIOLATION_KEYS}
        return info

    def reset(self, *, seed=None, options=None):
        self._states = self._do_reset(seed)
        self._t[:] = 0
        return np.asarray(self._states.obs, np.float32), self._reset_info(self._states)

    def step(self, actions):
        a = jnp.asarray(np.asarray(actions, np.float32).reshape(self.num_envs, self._n))
        self._states = self._step_fn(self._states, a)
        self._t += 1
        obs = np.asarray(self._states.obs, np.float32)
        reward = np.asarray(self._states.reward, np.float64)
        terminated = np.zeros(self.num_envs, bool)
        truncated = self._t >= self.max_episode_steps
        info = _infos(self._states)
        if truncated.any():
            final_obs = np.full(self.num_envs, None, dtype=object)
            for i in np.flatnonzero(truncated):
                final_obs[i] = obs[i].copy()
            final_info = info
            self._key, sub = jax.random.split(self._key)
            fresh = self._reset_fn(jax.random.split(sub, self.num_envs))
            mask = jnp.asarray(truncated)
            self._states = jax.tree.map(
                lambda f, s: jnp.where(mask.reshape((-1,) + (1,) * (s.ndim - 1)), f, s), fresh, self._states
            )
            obs = np.asarray(self._states.obs, np.float32)
            self._t[truncated] = 0
            # top-level info of the reset envs: the fresh state's, as Gymnasium's SAME_STEP autoreset gives
            info = jax.tree.map(
                lambda r, f: np.where(truncated.reshape((-1,) + (1,) * (f.ndim - 1)), r, f),
                self._reset_info(self._states),
                final_info,
            )
            info.update(
                final_obs=final_obs, _final_obs=truncated.copy(), final_info=final_info, _final_info=truncated.copy()
            )
        return obs, reward, terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array" or self._states is None:
            return None
        return tuple(self._frame(i) for i in range(self.num_envs))

    def close_extras(self, **kwargs):
        self._close_renderer()


def register_envs():
    """Register ``jaxlimits/PlanarReach-v0`` and ``jaxlimits/PandaReach-v0`` (idempotent)."""
    for name, arm in (("PlanarReach", "planar"), ("PandaReach", "panda")):
        env_id = f"jaxlimits/{name}-v0"
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="jaxlimits.envs.gym:ArmEnv",
            vector_entry_point="jaxlimits.envs.gym:ArmVectorEnv",
            max_episode_steps=500,
            kwargs={"arm": arm},
        )


register_envs()

__all__ = ["ArmEnv", "ArmVectorEnv", "JointLimitShieldWrapper", "NonFiniteActionGuardWrapper", "register_envs"]

from jaxlimits.envs.gym_nonfinite_guard import NonFiniteActionGuardWrapper  # noqa: E402
from jaxlimits.envs.gym_shield import JointLimitShieldWrapper  # noqa: E402
