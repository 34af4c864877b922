"""The smallest Gymnasium ``MujocoEnv`` over an MJCF file, for the tests that shield a model of their own."""

import mujoco
import numpy as np
from gymnasium.envs.mujoco import MujocoEnv
from gymnasium.spaces import Box


class SmallMujocoEnv(MujocoEnv):
    """``path``'s model, 5 substeps per step, the action its ``ctrl``, observation ``(qpos, qvel)``, no reward, no
    termination. ``reset_qpos(np_random) -> (nq,)``: the reset's joint positions (default the model's ``qpos0``),
    velocities zero."""

    metadata = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"], "render_fps": 100}

    def __init__(self, path, reset_qpos=None):
        model = mujoco.MjModel.from_xml_path(str(path))
        obs = Box(-np.inf, np.inf, (model.nq + model.nv,), np.float64)
        MujocoEnv.__init__(self, str(path), 5, observation_space=obs)
        self._reset_qpos = reset_qpos

    def step(self, action):
        self.do_simulation(action, self.frame_skip)
        return self._get_obs(), 0.0, False, False, {}

    def _get_obs(self):
        return np.concatenate([self.data.qpos, self.data.qvel])

    def reset_model(self):
        q = self.init_qpos if self._reset_qpos is None else self._reset_qpos(self.np_random)
        self.set_state(q, self.init_qvel)
        return self._get_obs()
