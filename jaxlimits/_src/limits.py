"""Joint limits: an immutable pytree validated eagerly when it is built from concrete values."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from jaxlimits._src.tracing import is_traced

_FIELDS = ("q_min", "q_max", "v_max", "a_max", "j_max")


def _as_concrete(name: str, value: Any) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"JointLimits.{name} must be a real number or array, got {value!r}") from exc
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"JointLimits.{name} must be finite, got {value!r}")
    return arr


@jax.tree_util.register_pytree_node_class
class JointLimits:
    """Per-joint limits of position, velocity, acceleration and (optionally) jerk.

    Args (each a scalar or an array of shape ``(n,)``; they are broadcast together):
      q_min, q_max: position limits [rad or m], ``q_min < q_max``.
      v_max: velocity limit [rad/s], symmetric ``|v| <= v_max``, ``> 0``.
      a_max: acceleration limit [rad/s^2], symmetric, ``> 0``.
      j_max: jerk limit [rad/s^3], symmetric, ``> 0``; ``None`` for no jerk limit.

    Concrete inputs are checked here, before any tracing: NaN/inf, ``q_min >= q_max``,
    non-positive ``v_max``/``a_max``/``j_max`` and shapes that do not broadcast raise ``ValueError``
    naming the field and its value. Values are stored as float64 NumPy arrays and cast to the
    dtype of the state when bounds are computed. Inside ``jit``/``vmap`` (tracer fields, e.g. limits
    passed as a jitted argument) no check is possible; build the limits outside.
    """

    __slots__ = _FIELDS

    def __init__(self, q_min, q_max, v_max, a_max, j_max=None):
        values = {"q_min": q_min, "q_max": q_max, "v_max": v_max, "a_max": a_max}
        if j_max is not None:
            values["j_max"] = j_max
        if any(is_traced(v) for v in values.values()):
            for name in _FIELDS:
                object.__setattr__(self, name, values.get(name))
            return
        arrays = {name: _as_concrete(name, v) for name, v in values.items()}
        for name, arr in arrays.items():
            if arr.ndim > 1:
                raise ValueError(f"JointLimits.{name} must be a scalar or a 1-D array, got shape {arr.shape}")
        try:
            shape = np.broadcast_shapes(*(a.shape for a in arrays.values()))
        except ValueError as exc:
            shapes = {k: a.shape for k, a in arrays.items()}
            raise ValueError(f"JointLimits fields have shapes that do not broadcast: {shapes}") from exc
        arrays = {k: np.broadcast_to(a, shape).copy() for k, a in arrays.items()}
        bad = arrays["q_min"] >= arrays["q_max"]
        if np.any(bad):
            raise ValueError(
                "JointLimits needs q_min < q_max, got q_min="
                f"{arrays['q_min'].tolist()} q_max={arrays['q_max'].tolist()} (joints {np.flatnonzero(bad).tolist()})"
            )
        for name in ("v_max", "a_max", "j_max"):
            if name in arrays and np.any(arrays[name] <= 0):
                raise ValueError(f"JointLimits.{name} must be > 0, got {arrays[name].tolist()}")
        for name in _FIELDS:
            object.__setattr__(self, name, arrays.get(name))

    def __setattr__(self, name, value):
        raise AttributeError("JointLimits is immutable; use .replace(...)")

    def __reduce__(self):
        # pickle, copy and deepcopy rebuild through the constructor (validated again); without this they set the
        # slots one by one and hit __setattr__ (worker processes of vector envs pickle what their env needs)
        return JointLimits, tuple(getattr(self, name) for name in _FIELDS)

    def replace(self, **changes) -> "JointLimits":
        """A copy with some fields changed (validated again)."""
        fields = {name: getattr(self, name) for name in _FIELDS}
        fields.update(changes)
        return JointLimits(**fields)

    @property
    def n(self) -> int:
        """Number of joints described (1 for scalar limits)."""
        shape = np.shape(self.q_min)
        return shape[0] if shape else 1

    @property
    def concrete(self) -> bool:
        """True when every field holds concrete values (not tracers)."""
        return not any(is_traced(getattr(self, f)) for f in _FIELDS)

    def tree_flatten(self):
        has_jerk = self.j_max is not None
        leaves = [self.q_min, self.q_max, self.v_max, self.a_max] + ([self.j_max] if has_jerk else [])
        return leaves, has_jerk

    @classmethod
    def tree_unflatten(cls, has_jerk, leaves):
        obj = object.__new__(cls)
        for name, leaf in zip(_FIELDS, list(leaves) + ([] if has_jerk else [None])):
            object.__setattr__(obj, name, leaf)
        return obj

    def __repr__(self) -> str:
        body = ", ".join(
            f"{f}={np.asarray(getattr(self, f)).tolist() if self.concrete else getattr(self, f)}"
            for f in _FIELDS
            if getattr(self, f) is not None
        )
        return f"JointLimits({body})"
