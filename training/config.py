"""Run configurations: JSON files in ``training/configs/``, validated eagerly, overridable from the CLI.

A config names the env, the algorithm, the shield and every hyperparameter; the run folder stores
the resolved config next to the metrics so that a run can be repeated and its checkpoint rebuilt.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
ENVS = (
    "planar_reach",
    "panda_reach",
    "panda_front_reach",
    "planar_wall",
    "servo_panda_front_reach",
    "planar_robot_reach",
    "planar_robot_wall",
)
# envs with contacts: the impact-aware speed cap applies (``impact``)
CONTACT_ENVS = ("planar_wall", "planar_robot_wall")
# envs over any robot (``jaxlimits.envs.reach.Reach`` inside ``JointLimitShield``, the one shield): the shield any of
# ``JointLimitShield``'s methods, the actions per env, the first the default: the servo Panda's actuators' own
# commands; the planar arm's joint accelerations (``Reach(action="acceleration")``) or velocities tracked through them
ROBOT_ACTION_MODES = {
    "servo_panda_front_reach": ("servo_offset", "ctrl"),
    "planar_robot_reach": ("acceleration", "velocity"),
    "planar_robot_wall": ("acceleration", "velocity"),  # WallStrike's task over the planar arm (envs/strike.py)
}
ROBOT_ENVS = tuple(ROBOT_ACTION_MODES)
REACH_ENVS = tuple(e for e in ENVS if e not in CONTACT_ENVS)  # the reach tasks (success = final distance)
ALGOS = ("ppo", "apg")
SHIELDS = ("none", "clip", "naive", "viability", "jerk")
ARM_ACTION_MODES = (
    "acceleration",
    "velocity",
    "task_space",
)  # jaxlimits.envs.actions.ACTION_MODES (not imported: no MuJoCo here)
SERVO_ACTION_MODES = ("ctrl", "servo_offset", "acceleration")  # jaxlimits.envs.reach.ACTIONS
SERVO_SHIELDS = ("none", "naive", "viability", "jerk")  # jaxlimits.envs.joint_shield.METHODS
SHIELD_GRADIENTS = ("exact", "straight_through", "exact_fixed_bounds")  # envs.safety.SHIELD_GRADIENTS


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
class APGConfig:
    """Brax APG hyperparameters (names as in ``brax.training.agents.apg.train.train``).

    Each policy update differentiates the mean reward of ``horizon_length`` env steps of
    ``num_envs`` envs through the simulator *and the shield* (the projection's derivative);
    ``num_timesteps / (num_envs * horizon_length)`` updates are made. ``shield_gradient``: the
    derivative of the shield's projection the gradient goes through, ``"exact"`` (a clipped joint
    passes none), ``"straight_through"`` (identity; a heuristic) or ``"exact_fixed_bounds"`` (exact, the
    bounds held constant); see ``SafetyWrapper``.
    """

    num_envs: int = 64
    horizon_length: int = 32
    learning_rate: float = 1e-3
    schedule_decay: float = 0.999
    max_gradient_norm: float = 1e9
    action_repeat: int = 1
    normalize_observations: bool = True
    num_evals: int = 11
    num_eval_envs: int = 128
    policy_hidden: tuple = (64, 64)
    shield_gradient: str = "exact"


@dataclass(frozen=True)
class RunConfig:
    """One training run."""

    env: str = "planar_reach"
    algo: str = "ppo"
    shield: str = "viability"
    action_mode: str = "acceleration"
    ik_observation: bool = False
    precision_reward: float = 0.0
    impact: bool = False
    num_timesteps: int = 5_000_000
    episode_length: int = 200
    seed: int = 0
    eval_episodes: int = 10_000
    ppo: PPOConfig = field(default_factory=PPOConfig)
    apg: APGConfig = field(default_factory=APGConfig)

    @property
    def action_repeat(self) -> int:
        """The action repeat of the configured algorithm."""
        return getattr(self, self.algo).action_repeat

    @property
    def num_eval_envs(self) -> int:
        """Episodes of the evaluations made during training."""
        return getattr(self, self.algo).num_eval_envs

    def __post_init__(self):
        if self.env not in ENVS:
            raise ValueError(f"config field 'env' must be one of {ENVS}, got {self.env!r}")
        servo = self.env in ROBOT_ENVS
        for name, value, allowed in (
            ("action_mode", self.action_mode, ROBOT_ACTION_MODES[self.env] if servo else ARM_ACTION_MODES),
            ("shield", self.shield, SERVO_SHIELDS if servo else SHIELDS),
            ("algo", self.algo, ("ppo",) if servo else ALGOS),
        ):
            if value not in allowed:
                raise ValueError(f"config field {name!r} must be one of {allowed} for env {self.env!r}, got {value!r}")
        for name in ("num_timesteps", "episode_length", "eval_episodes"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"config field {name!r} must be a positive integer, got {value!r}")
        if not (isinstance(self.precision_reward, (int, float)) and self.precision_reward >= 0):
            raise ValueError(f"config field 'precision_reward' must be a number >= 0, got {self.precision_reward!r}")
        for name in ("ik_observation", "impact"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"config field {name!r} must be true or false, got {getattr(self, name)!r}")
        if self.impact and self.env not in CONTACT_ENVS:
            raise ValueError(f"config field 'impact' needs an env with contacts {CONTACT_ENVS}, got env {self.env!r}")
        if self.env in CONTACT_ENVS and (self.ik_observation or self.precision_reward):
            raise ValueError(
                f"config fields 'ik_observation' and 'precision_reward' are reach options; env {self.env!r} has its "
                f"own observation and reward (got {self.ik_observation!r}, {self.precision_reward!r})"
            )
        for section in ("ppo", "apg"):
            _check_section(section, getattr(self, section))
        p = self.ppo
        if p.batch_size * p.num_minibatches % p.num_envs:
            raise ValueError(
                f"ppo.batch_size * ppo.num_minibatches ({p.batch_size * p.num_minibatches}) must be a "
                f"multiple of ppo.num_envs ({p.num_envs}) (Brax PPO's requirement)"
            )
        if self.episode_length % self.action_repeat:
            raise ValueError(
                f"episode_length ({self.episode_length}) must be a multiple of {self.algo}.action_repeat "
                f"({self.action_repeat})"
            )
        a = self.apg
        if a.shield_gradient not in SHIELD_GRADIENTS:
            raise ValueError(
                f"config field 'apg.shield_gradient' must be one of {SHIELD_GRADIENTS}, got {a.shield_gradient!r}"
            )
        if a.horizon_length % a.action_repeat:
            raise ValueError(
                f"apg.horizon_length ({a.horizon_length}) must be a multiple of apg.action_repeat ({a.action_repeat})"
            )

    def to_dict(self) -> dict:
        d = asdict(self)
        for section in ("ppo", "apg"):
            for key, value in d[section].items():
                if isinstance(value, tuple):
                    d[section][key] = list(value)
        return d

    def override(self, **kwargs) -> "RunConfig":
        """A copy with the non-``None`` fields replaced (the CLI's flags), validated again; ``ppo=`` and
        ``apg=`` take a dict of that section's fields to replace (the others kept), e.g.
        ``cfg.override(num_timesteps=640, apg={"num_evals": 3})``."""
        d = self.to_dict()
        for key, value in kwargs.items():
            if value is not None:
                d[key] = {**d[key], **value} if key in _SECTIONS else value
        return from_dict(d)


def _check_section(section: str, cfg) -> None:
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if f.type in (int, "int") and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
            raise ValueError(f"config field '{section}.{f.name}' must be a positive integer, got {value!r}")
        if f.type in (float, "float") and not (
            isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0
        ):
            raise ValueError(f"config field '{section}.{f.name}' must be a non-negative number, got {value!r}")
        if f.type in (bool, "bool") and not isinstance(value, bool):
            raise ValueError(f"config field '{section}.{f.name}' must be true or false, got {value!r}")
        if f.type in (tuple, "tuple") and not (value and all(isinstance(x, int) and x > 0 for x in value)):
            raise ValueError(f"config field '{section}.{f.name}' must be a list of positive layer sizes, got {value!r}")


_SECTIONS = {"ppo": PPOConfig, "apg": APGConfig}


def from_dict(d: dict) -> RunConfig:
    """Build (and validate) a ``RunConfig``; unknown keys raise with their names."""
    d = dict(d)
    sections = {name: dict(d.pop(name, {})) for name in _SECTIONS}
    unknown = sorted(set(d) - {f.name for f in fields(RunConfig)})
    for name, cls in _SECTIONS.items():
        known = {f.name for f in fields(cls)}
        unknown += sorted(f"{name}.{k}" for k in set(sections[name]) - known)
        for f in fields(cls):
            if f.type in (tuple, "tuple") and isinstance(sections[name].get(f.name), list):
                sections[name][f.name] = tuple(sections[name][f.name])
    if unknown:
        raise ValueError(f"unknown config fields {unknown}")
    return RunConfig(**d, **{name: cls(**sections[name]) for name, cls in _SECTIONS.items()})


def load(name_or_path) -> RunConfig:
    """A config from a JSON file path, or by name from ``training/configs/`` (``"planar_reach_ppo"``)."""
    path = Path(name_or_path)
    if not path.suffix:
        path = CONFIG_DIR / f"{name_or_path}.json"
    if not path.is_file():
        available = sorted(p.stem for p in CONFIG_DIR.glob("*.json"))
        raise FileNotFoundError(f"no config {name_or_path!r} (file {path}); available: {available}")
    return from_dict(json.loads(path.read_text()))
