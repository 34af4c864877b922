"""Caches keyed on content: arrays by dtype, shape and bytes, models and pytrees by a digest of everything in them,
and the bounded LRU they are kept in.

Whatever is computed from a model alone (its MJX stages' traces, a robot read from it, a shield's compiled
decision) serves every object of equal content: the users' and tests' envs rebuild the same model many times
(one per env copy, fixture or run), and each rebuild would otherwise redo seconds of work."""

from __future__ import annotations

import collections
import dataclasses
import enum
import hashlib

import jax
import mujoco
import numpy as np


class LruCache:
    """A dict of at most ``size`` entries that forgets the least recently used one (``get`` and ``put`` use)."""

    def __init__(self, size: int):
        if size < 1:
            raise ValueError(f"LruCache size must be >= 1, got {size!r}")
        self.size = size
        self._entries: collections.OrderedDict = collections.OrderedDict()

    def get(self, key, default=None):
        if key not in self._entries:
            return default
        self._entries.move_to_end(key)
        return self._entries[key]

    def put(self, key, value) -> None:
        self._entries[key] = value
        self._entries.move_to_end(key)
        if len(self._entries) > self.size:
            self._entries.popitem(last=False)

    def __contains__(self, key) -> bool:
        return key in self._entries

    def __len__(self) -> int:
        return len(self._entries)


def array_key(x) -> tuple:
    """``(dtype, shape, bytes)`` of an array-like (NumPy, JAX or a scalar): equal exactly for equal contents."""
    a = np.ascontiguousarray(x)
    return a.dtype.str, a.shape, a.tobytes()


def model_bytes(mj_model: mujoco.MjModel) -> np.ndarray:
    """The model's MJB serialisation (``mj_saveModel``): equal for models of equal content, ``(size,) uint8``."""
    buf = np.empty(mujoco.mj_sizeModel(mj_model), np.uint8)
    mujoco.mj_saveModel(mj_model, None, buf)
    return buf


def content_digest(tree) -> str:
    """SHA-1 over everything in ``tree``: dataclasses field by field (an MJX ``Model``, a Brax ``System``, static
    fields included), tuples, lists, dicts, arrays (``array_key``), ``MjModel`` s (``model_bytes``), enums and
    plain scalars, each with its type. Raises ``TypeError`` for any other object (its content is unknown, so
    nothing may be shared on its account)."""
    h = hashlib.sha1()
    _feed(h, tree)
    return h.hexdigest()


def _feed(h, x) -> None:
    if x is None or isinstance(x, (bool, int, float, str, bytes, enum.Enum)):
        h.update(repr((type(x).__qualname__, x)).encode())
    elif isinstance(x, (np.ndarray, np.generic, jax.Array)):
        dtype, shape, data = array_key(x)
        h.update(repr(("array", dtype, shape)).encode())
        h.update(data)
    elif isinstance(x, mujoco.MjModel):
        data = model_bytes(x)
        h.update(repr(("MjModel", data.size)).encode())
        h.update(data)
    elif dataclasses.is_dataclass(x) and not isinstance(x, type):
        h.update(repr(("dataclass", type(x).__module__, type(x).__qualname__)).encode())
        for f in dataclasses.fields(x):
            h.update(repr(("field", f.name)).encode())
            _feed(h, getattr(x, f.name))
    elif isinstance(x, (tuple, list)):
        h.update(repr((type(x).__qualname__, len(x))).encode())
        for item in x:
            _feed(h, item)
    elif isinstance(x, dict):
        h.update(repr(("dict", len(x))).encode())
        for k in sorted(x, key=repr):
            _feed(h, k)
            _feed(h, x[k])
    else:
        raise TypeError(f"content_digest: no content key for a {type(x).__module__}.{type(x).__qualname__}")
