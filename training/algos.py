"""One entry point per algorithm: ``train(cfg, run_dir)`` and ``load_policy(run_dir)`` dispatch on ``cfg.algo``.

``ppo``: ``brax_ppo`` (the shield inside the env); ``apg``: ``brax_apg`` (the shield inside the
differentiated path). Both write the same run folder and return the same summary.
"""

from __future__ import annotations

import importlib
from pathlib import Path

from jaxlimits.training import checkpoint
from jaxlimits.training.config import from_dict

_MODULES = {"ppo": "jaxlimits.training.brax_ppo", "apg": "jaxlimits.training.brax_apg"}


def module(algo: str):
    """The training module of ``algo``."""
    if algo not in _MODULES:
        raise ValueError(f"algo must be one of {tuple(_MODULES)}, got {algo!r}")
    return importlib.import_module(_MODULES[algo])


def train(cfg, run_dir, show_progress: bool = True) -> dict:
    """Train ``cfg`` with its algorithm; see ``brax_ppo.train``."""
    return module(cfg.algo).train(cfg, run_dir, show_progress=show_progress)


def load_policy(run_dir):
    """``(cfg, policy, params)`` of a run folder of either algorithm."""
    cfg = from_dict(checkpoint.read_meta(Path(run_dir) / "params.msgpack"))
    return module(cfg.algo).load_policy(run_dir)
