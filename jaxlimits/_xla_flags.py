"""XLA flags that MuJoCo-MJX needs on a CPU, set before JAX is first imported.

Without ``--xla_cpu_use_fusion_emitters=false`` XLA's CPU fusion emitters make MJX kinematics of a
7-joint arm about 100x slower (jax issue 33761). This module imports nothing from JAX so that it
can run first; flags a user already set are kept, including an explicit ``...=true``.

The flag is set only for the jaxlib releases it was measured with (``CPU_FLAGS_JAXLIB``: 0.9.x, the
pinned one): jaxlib 0.11.2's XLA no longer knows it and aborts the process at its first backend
("Unknown flag in XLA_FLAGS"; seen on a GPU machine), so a newer jaxlib gets no flag from here.
"""

from __future__ import annotations

import importlib.metadata
import os
import sys
import warnings

CPU_FLAGS = {"xla_cpu_use_fusion_emitters": "false"}
CPU_FLAGS_JAXLIB = ((0, 9),)  # (major, minor) releases of jaxlib whose XLA knows CPU_FLAGS (measured)


def cpu_flags_known(jaxlib_version: str | None) -> bool:
    """Whether ``CPU_FLAGS`` are known to the XLA of jaxlib ``jaxlib_version`` (e.g. ``"0.9.2"``; None:
    jaxlib is not installed, nothing to break)."""
    if jaxlib_version is None:
        return True
    try:
        major, minor = (int(x) for x in jaxlib_version.split(".")[:2])
    except ValueError:
        return False
    return (major, minor) in CPU_FLAGS_JAXLIB


def _installed_jaxlib() -> str | None:
    try:
        return importlib.metadata.version("jaxlib")
    except importlib.metadata.PackageNotFoundError:
        return None


def merged_xla_flags(existing: str, jaxlib_version: str | None = None) -> str:
    """Return ``existing`` XLA_FLAGS with our CPU flags appended where the user did not set them (none for a
    ``jaxlib_version`` whose XLA does not know them: ``cpu_flags_known``)."""
    if not cpu_flags_known(jaxlib_version):
        return existing
    parts = existing.split()
    present = {p.lstrip("-").split("=", 1)[0] for p in parts}
    parts += [f"--{name}={value}" for name, value in CPU_FLAGS.items() if name not in present]
    return " ".join(parts)


def set_cpu_xla_flags() -> bool:
    """Put the CPU flags into ``os.environ['XLA_FLAGS']``; return False if it is too late.

    XLA reads XLA_FLAGS when JAX starts its first backend (the first computation), not at
    ``import jax``. If a backend is already running and the flags were not already set, they cannot take
    effect; a warning says so. (Set already, e.g. by an earlier ``import jaxlimits``, they are in effect: no
    warning. It warned before, a false alarm on ``import jaxlimits.envs`` after some JAX work.)
    """
    before = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = merged_xla_flags(before, _installed_jaxlib())
    if os.environ["XLA_FLAGS"] != before and _jax_backend_started():
        current = os.environ["XLA_FLAGS"]
        warnings.warn(
            "jax was imported before jaxlimits could set XLA_FLAGS="
            f"'{current}'; MJX on a CPU may run ~100x slower. Import jaxlimits first or export "
            "XLA_FLAGS=--xla_cpu_use_fusion_emitters=false before starting Python.",
            RuntimeWarning,
            stacklevel=3,
        )
        return False
    return True


def _jax_backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge  # private, but the only way to ask without starting one

        return bool(xla_bridge._backends)
    except (ImportError, AttributeError):
        return True
