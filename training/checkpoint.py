"""Save and load policy parameters as msgpack (flax.serialization): data only, nothing runs on load.

A checkpoint is one ``.msgpack`` file holding ``{"params": <pytree of arrays>, "meta": <JSON
string>}``. ``meta`` records what is needed to rebuild the networks (the run config: env, algo,
network sizes) so that ``load`` needs no pickle and no code from the file. Loading restores the
arrays into a template pytree built by the caller (``flax.serialization.from_state_dict``), so a
file whose structure does not match raises instead of loading silently.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
from flax import serialization


def save(path, params, meta: dict) -> Path:
    """Write ``params`` (any pytree of arrays) and the JSON-serialisable ``meta`` to ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = serialization.to_state_dict(jax.tree.map(np.asarray, params))
    blob = serialization.msgpack_serialize({"params": state, "meta": json.dumps(meta, sort_keys=True)})
    path.write_bytes(blob)
    return path


def read_meta(path) -> dict:
    """The ``meta`` dict of a checkpoint (the run config), without restoring the parameters."""
    return json.loads(_raw(path)["meta"])


def load(path, template):
    """The parameters of a checkpoint, restored into the structure of ``template`` (a pytree).

    Raises ``ValueError`` if the file is not a jaxlimits checkpoint or its structure differs.
    """
    raw = _raw(path)
    try:
        return serialization.from_state_dict(template, raw["params"])
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"checkpoint {path} does not match the expected parameter structure: {exc}") from exc


def _raw(path) -> dict:
    data = Path(path).read_bytes()
    try:
        raw = serialization.msgpack_restore(data)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise ValueError(f"{path} is not a msgpack checkpoint: {exc}") from exc
    if not isinstance(raw, dict) or set(raw) != {"params", "meta"}:
        raise ValueError(f"{path} is not a jaxlimits checkpoint (expected keys params, meta)")
    return raw
