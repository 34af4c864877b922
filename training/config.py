"""Run configurations: JSON files in ``training/configs/``, validated eagerly, overridable from the CLI.

A config names the env, the algorithm, the shield and every hyperparameter; the run folder stores
the resolved config next to the metrics so that a run can be repeated and its checkpoint rebuilt.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
ENVS = ("planar_reach", "panda_reach")
ALGOS = ("ppo",)
SHIELDS = ("none", "clip", "naive", "viability", "jerk")


@dataclass(frozen=True)
class PPOConfig:
    """Brax PPO hyperparameters (names as in ``brax.training.agents.ppo.train.train``)."""

    num_envs: int = 512
    batch_size: int = 256
    num_minibatches: int = 16
    unroll_length: int = 10
    num_updates_per_batch: int = 4
    learning_rate: float = 1e-3
    entropy_cost: float = 1e-2
    discounting: float = 0.99
    reward_scaling: float = 1.0
    action_repeat: int = 2
    normalize_observations: bool = True
    num_evals: int = 11
    num_eval_envs: int = 256
    policy_hidden: tuple = (64, 64)
    value_hidden: tuple = (64, 64)


@dataclass(frozen=True)
class RunConfig:
    """One training run."""

    env: str = "planar_reach"
    algo: str = "ppo"
    shield: str = "viability"
    num_timesteps: int = 5_000_000
    episode_length: int = 200
    seed: int = 0
    eval_episodes: int = 10_000
    ppo: PPOConfig = field(default_factory=PPOConfig)

    def __post_init__(self):
        checks = [("env", self.env, ENVS), ("algo", self.algo, ALGOS), ("shield", self.shield, SHIELDS)]
        for name, value, allowed in checks:
            if value not in allowed:
                raise ValueError(f"config field {name!r} must be one of {allowed}, got {value!r}")
        for name in ("num_timesteps", "episode_length", "eval_episodes"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"config field {name!r} must be a positive integer, got {value!r}")
        p = self.ppo
        for f in fields(PPOConfig):
            value = getattr(p, f.name)
            if f.type in (int, "int") and (not isinstance(value, int) or value < 1):
                raise ValueError(f"config field 'ppo.{f.name}' must be a positive integer, got {value!r}")
            if f.type in (float, "float") and not (isinstance(value, (int, float)) and value >= 0):
                raise ValueError(f"config field 'ppo.{f.name}' must be a non-negative number, got {value!r}")
        if p.batch_size * p.num_minibatches % p.num_envs:
            raise ValueError(f"ppo.batch_size * ppo.num_minibatches ({p.batch_size * p.num_minibatches}) must be a "
                             f"multiple of ppo.num_envs ({p.num_envs}) (Brax PPO's requirement)")
        if self.episode_length % p.action_repeat:
            raise ValueError(f"episode_length ({self.episode_length}) must be a multiple of ppo.action_repeat "
                             f"({p.action_repeat})")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["ppo"]["policy_hidden"] = list(self.ppo.policy_hidden)
        d["ppo"]["value_hidden"] = list(self.ppo.value_hidden)
        return d

    def override(self, **kwargs) -> "RunConfig":
        """A copy with the non-``None`` top-level fields replaced (the CLI's flags)."""
        return replace(self, **{k: v for k, v in kwargs.items() if v is not None})


def from_dict(d: dict) -> RunConfig:
    """Build (and validate) a ``RunConfig``; unknown keys raise with their names."""
    d = dict(d)
    ppo = dict(d.pop("ppo", {}))
    known = {f.name for f in fields(RunConfig)}
    known_ppo = {f.name for f in fields(PPOConfig)}
    unknown = sorted(set(d) - known) + sorted(f"ppo.{k}" for k in set(ppo) - known_ppo)
    if unknown:
        raise ValueError(f"unknown config fields {unknown}")
    for key in ("policy_hidden", "value_hidden"):
        if key in ppo:
            ppo[key] = tuple(int(x) for x in ppo[key])
    return RunConfig(**d, ppo=PPOConfig(**ppo))


def load(name_or_path) -> RunConfig:
    """A config from a JSON file path, or by name from ``training/configs/`` (``"planar_reach_ppo"``)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = CONFIG_DIR / f"{name_or_path}.json"
    if not path.is_file():
        available = sorted(p.stem for p in CONFIG_DIR.glob("*.json"))
        raise FileNotFoundError(f"no config {name_or_path!r} (file {path}); available: {available}")
    return from_dict(json.loads(path.read_text()))
