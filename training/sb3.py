"""Stable-Baselines3 PPO and SAC on the Gymnasium front, violations counted from ``info["violation"]``.

``train(shield, total_timesteps, out, algo="ppo"|"sac")`` trains SB3's ``PPO("MlpPolicy")`` or
``SAC("MlpPolicy")`` (torch, CPU) on
``gymnasium.make("jaxlimits/PlanarReach-v0", shield=shield)`` and writes to ``out``:
``policy.npz`` (the policy's ``state_dict`` as arrays: no pickle, unlike SB3's ``.zip``),
``metrics.json`` (env-steps, violation counts and maxima from every step's ``info["violation"]``,
episode returns) and returns the model. ``load_policy_arrays`` reads ``policy.npz`` back into a
fresh SB3 policy.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxlimits.envs.arm import VIOLATION_KEYS


def _make_env(shield: str, arm: str, max_episode_steps: int, **task):
    import gymnasium

    import jaxlimits.envs.gym as jgym

    jgym.register_envs()
    name = {"planar": "jaxlimits/PlanarReach-v0", "panda": "jaxlimits/PandaReach-v0"}[arm]
    return gymnasium.make(name, shield=shield, max_episode_steps=max_episode_steps, **task)


class _ViolationCounter:
    """An SB3 callback body: sums ``info["violation"][k] > 0`` over every env step."""

    def __init__(self):
        self.counts = {k: 0 for k in VIOLATION_KEYS}
        self.maxes = {k: 0.0 for k in VIOLATION_KEYS}
        self.env_steps = 0
        self.episode_returns = []

    def update(self, infos):
        for info in infos:
            self.env_steps += 1
            for k, x in info["violation"].items():
                self.counts[k] += int(x > 0)
                self.maxes[k] = max(self.maxes[k], float(x))
            if "episode" in info:
                self.episode_returns.append(float(info["episode"]["r"]))


ALGOS = ("ppo", "sac")


def silent_logger():
    """An SB3 ``Logger`` with no outputs. Without one, every ``learn`` with ``verbose=0`` and no ``tensorboard_log``
    creates an empty ``SB3-<timestamp>`` folder in the system's temporary directory (``logger.configure``)."""
    from stable_baselines3.common.logger import Logger

    return Logger(folder=None, output_formats=[])


def train(
    shield: str = "viability",
    total_timesteps: int = 20_000,
    out=None,
    *,
    algo: str = "ppo",
    arm: str = "planar",
    max_episode_steps: int = 200,
    seed: int = 0,
    n_steps: int = 512,
    batch_size: int = 64,
    learning_starts: int = 1000,
    **task,
):
    """Train SB3 PPO or SAC; returns ``(model, metrics)`` and writes ``out`` if given.

    ``n_steps`` is PPO's rollout length, ``learning_starts`` SAC's number of random steps before
    its first update; ``batch_size`` is either's minibatch. ``task`` goes to the Gymnasium env
    (``action_mode``, ``ik_observation``, ``precision_reward``: see ``jaxlimits.envs.gym``).
    """
    import torch
    from stable_baselines3 import PPO, SAC
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.monitor import Monitor

    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    torch.set_num_threads(1)
    counter = _ViolationCounter()

    class Callback(BaseCallback):
        def _on_step(self) -> bool:
            counter.update(self.locals["infos"])
            return True

    env = Monitor(_make_env(shield, arm, max_episode_steps, **task))
    common = dict(batch_size=batch_size, seed=seed, device="cpu", verbose=0, policy_kwargs={"net_arch": [64, 64]})
    if algo == "ppo":
        model = PPO("MlpPolicy", env, n_steps=n_steps, **common)
    else:
        model = SAC("MlpPolicy", env, learning_starts=learning_starts, **common)
    model.set_logger(silent_logger())
    model.learn(total_timesteps=total_timesteps, callback=Callback())
    metrics = {
        "algo": algo,
        "shield": shield,
        "arm": arm,
        "task": task,
        "env_steps": counter.env_steps,
        "episode_returns": counter.episode_returns,
        **{f"violations/{k}": v for k, v in counter.counts.items()},
        **{f"max_violation/{k}": v for k, v in counter.maxes.items()},
    }
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        arrays = {k: v.detach().cpu().numpy() for k, v in model.policy.state_dict().items()}
        np.savez(out / "policy.npz", **arrays)
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    env.close()
    return model, metrics


def load_policy_arrays(model, path) -> None:
    """Load ``policy.npz`` (written by ``train``) into ``model.policy`` (same architecture); no pickle."""
    import torch

    with np.load(path, allow_pickle=False) as data:
        state = {k: torch.from_numpy(data[k]) for k in data.files}
    model.policy.load_state_dict(state, strict=True)
