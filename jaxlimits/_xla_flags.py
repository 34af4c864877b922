"""XLA flags that MuJoCo-MJX needs on a CPU, set before JAX is first imported.

Without ``--xla_cpu_use_fusion_emitters=false`` XLA's CPU fusion emitters make MJX kinematics of a
7-joint arm about 100x slower (jax issue 33761). This module imports nothing from JAX so that it
can run first; flags a user already set are kept, including an explicit ``...=true``.
"""

from __future__ import annotations

import os
import sys
import warnings

CPU_FLAGS = {"xla_cpu_use_fusion_emitters": "false"}


def merged_xla_flags(existing: str) -> str:
    """Return ``existing`` XLA_FLAGS with our CPU flags appended where the user did not set them."""
    parts = existing.split()
    present = {p.lstrip("-").split("=", 1)[0] for p in parts}
    parts += [f"--{name}={value}" for name, value in CPU_FLAGS.items() if name not in present]
    return " ".join(parts)


def set_cpu_xla_flags() -> bool:
    """Put the CPU flags into ``os.environ['XLA_FLAGS']``; return False if it is too late.

    XLA reads XLA_FLAGS when JAX starts its first backend (the first computation), not at
    ``import jax``. If a backend is already running the flags cannot take effect; a warning says so.
    """
    os.environ["XLA_FLAGS"] = merged_xla_flags(os.environ.get("XLA_FLAGS", ""))
    if _jax_backend_started():
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
