"""Unstable building blocks for the project's own layers (benchmarks, envs, tests).

Not part of the public API: names here may change without notice. Everything a user needs is in
``jaxlimits``; this module exists so that ``envs/``, ``training/`` and ``benchmarks/`` never import
``jaxlimits._src`` directly.
"""

from jaxlimits._src.qp_linalg import chol_solve, masked_matrix
from jaxlimits._src.tracing import batched_like, is_traced

__all__ = ["batched_like", "chol_solve", "is_traced", "masked_matrix"]
