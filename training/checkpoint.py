"""Checksummed msgpack checkpoints (flax.serialization; data only, nothing runs on load) and atomic writes.

A checkpoint file is one header line and a msgpack payload::

    JAXLIMITS-CHECKPOINT 1 sha256=<64 hex digits> bytes=<payload length>\\n<payload>

The payload is ``{"params": <pytree of arrays>, "meta": <JSON string>}``. ``meta`` records what is
needed to rebuild the networks (the run config: env, algo, network sizes) so that ``load`` needs no
pickle and no code from the file. Reading checks the header, the length and the SHA-256 of the
payload before anything is decoded: a truncated, bit-flipped or foreign file raises ``ValueError``
naming the file, never a partial load. Loading restores the arrays into a template pytree built by
the caller (``flax.serialization.from_state_dict``), so a file whose structure does not match
raises instead of loading silently.

Every file goes through ``atomic_write_bytes`` / ``atomic_write_text``: a temporary file in the
same folder, flushed and fsynced, then ``os.replace``d over the target (and the folder fsynced), so
a process killed at any moment leaves either the old file or the new one, never a mix.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import tempfile
from pathlib import Path

import jax
import numpy as np
from flax import serialization

MAGIC = b"JAXLIMITS-CHECKPOINT 1"
_HEADER = re.compile(rb"JAXLIMITS-CHECKPOINT 1 sha256=([0-9a-f]{64}) bytes=([0-9]{1,15})\n")


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: temp file in the same folder + fsync + ``os.replace``.

    Readers (and a later run after a crash) see the old content or the new, never a truncated file.
    Creates the parent folder. Returns ``path`` as a ``Path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> Path:
    """``atomic_write_bytes`` for text (``results.json``, ``summary.json``, ``results.md``...)."""
    return atomic_write_bytes(path, text.encode(encoding))


def _fsync_dir(folder: Path) -> None:
    """Make the rename itself durable (POSIX); a no-op where folders cannot be opened (Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def save(path, params, meta: dict) -> Path:
    """Write ``params`` (any pytree of arrays) and the JSON-serialisable ``meta`` to ``path``, atomically."""
    state = serialization.to_state_dict(jax.tree.map(np.asarray, params))
    payload = serialization.msgpack_serialize({"params": state, "meta": json.dumps(meta, sort_keys=True)})
    header = MAGIC + b" sha256=" + hashlib.sha256(payload).hexdigest().encode() + b" bytes=%d\n" % len(payload)
    return atomic_write_bytes(path, header + payload)


def read_meta(path) -> dict:
    """The ``meta`` dict of a checkpoint (the run config), without restoring the parameters."""
    return json.loads(_raw(path)["meta"])


def load(path, template):
    """The parameters of a checkpoint, restored into the structure of ``template`` (a pytree).

    Raises ``ValueError`` naming the file if it is not a jaxlimits checkpoint, is truncated or
    corrupted (checksum), or its structure differs from ``template``.
    """
    raw = _raw(path)
    try:
        return serialization.from_state_dict(template, raw["params"])
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"checkpoint {path} does not match the expected parameter structure: {exc}") from exc


def load_with_meta(path, template):
    """``(params, meta)`` of a checkpoint from one read (one checksum check)."""
    raw = _raw(path)
    try:
        params = serialization.from_state_dict(template, raw["params"])
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"checkpoint {path} does not match the expected parameter structure: {exc}") from exc
    return params, json.loads(raw["meta"])


def _raw(path) -> dict:
    data = Path(path).read_bytes()
    end = data.find(b"\n", 0, 200)
    match = _HEADER.fullmatch(data[: end + 1]) if end >= 0 else None
    if match is None:
        if not data.startswith(MAGIC):
            raise ValueError(f"{path} is not a jaxlimits checkpoint (no '{MAGIC.decode()}' header)")
        raise ValueError(f"checkpoint {path} is corrupted: its header is damaged")
    payload = data[end + 1 :]
    expected = int(match.group(2))
    if len(payload) != expected:
        raise ValueError(
            f"checkpoint {path} is truncated or corrupted: {len(payload)} payload bytes, the header says {expected}"
        )
    if hashlib.sha256(payload).hexdigest() != match.group(1).decode():
        raise ValueError(f"checkpoint {path} is corrupted: the SHA-256 of its payload does not match its header")
    try:
        raw = serialization.msgpack_restore(payload)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise ValueError(f"{path} is not a msgpack checkpoint: {exc}") from exc
    if not isinstance(raw, dict) or set(raw) != {"params", "meta"}:
        raise ValueError(f"{path} is not a jaxlimits checkpoint (expected keys params, meta)")
    return raw
