"""A clear error instead of a hang: JAX in a process forked after JAX had started.

JAX's runtime is multithreaded; a process made by ``os.fork()`` after the parent started it (ran any
computation) inherits its locks but not its threads, and its first JAX call blocks forever (measured
here: a jitted function in the child of such a fork hangs; ``jax.extend.backend.clear_backends()`` there
aborts the child). Gymnasium's ``AsyncVectorEnv`` forks by default on Linux, after building one env in the
parent (for its spaces): with a Gymnasium env that computes with JAX (``JointLimitShieldWrapper``'s decision,
``ArmEnv``'s physics) every worker hung without a message. The Gymnasium envs call
``check_not_forked_from_jax`` before their first JAX call, which raises ``RuntimeError`` naming the start
methods that work: ``AsyncVectorEnv(env_fns, context="forkserver")`` (or ``"spawn"``), and
Stable-Baselines3's ``SubprocVecEnv``, whose default start method is ``forkserver``.

The parent's state is read just before each fork (``os.register_at_fork(before=...)``, in the parent, where
JAX's lock is safe to take) and inherited by the child, which compares its own pid with the recorded one.
"""

from __future__ import annotations

import os

START_METHODS = (
    "Start the workers with 'forkserver' or 'spawn' instead of 'fork': gymnasium.vector.AsyncVectorEnv(env_fns, "
    "context='forkserver'), or stable_baselines3's SubprocVecEnv (forkserver by default)"
)
_at_fork = {"pid": None, "jax_started": False}  # the forking process's pid and whether its JAX had started


def _jax_started() -> bool:
    """Whether this process's JAX backends are initialised (a computation ran). JAX has no public name for it:
    ``jax._src.xla_bridge.backends_are_initialized`` (JAX 0.9); if it is gone, assume they are (an error, not a
    hang)."""
    import sys

    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge

    started = getattr(xla_bridge, "backends_are_initialized", None)
    return True if started is None else bool(started())


def _record_before_fork() -> None:
    _at_fork["pid"] = os.getpid()
    _at_fork["jax_started"] = _jax_started()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_record_before_fork)


def forked_from_jax() -> bool:
    """True in a process made by ``os.fork()`` from one whose JAX had started (its JAX calls would hang)."""
    return _at_fork["pid"] is not None and _at_fork["pid"] != os.getpid() and _at_fork["jax_started"]


def check_not_forked_from_jax(what: str) -> None:
    """Raise ``RuntimeError`` if ``forked_from_jax()``; ``what`` names the object being built."""
    if forked_from_jax():
        raise RuntimeError(
            f"{what} computes with JAX, and this process was forked (os.fork) from one in which JAX had already "
            f"started (pid {_at_fork['pid']}): JAX's first call here would block forever. {START_METHODS}"
        )
