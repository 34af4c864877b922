"""``envs/content_cache``: content keys equal exactly for equal contents (arrays, models, dataclasses, enums), refuse
objects of unknown content, and the LRU forgets the least recently used entry."""

import dataclasses
import enum
import pathlib

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from jaxlimits.envs.content_cache import LruCache, array_key, content_digest, model_bytes

PLANAR = pathlib.Path(__file__).resolve().parents[1] / "envs" / "assets" / "planar3.xml"


class Colour(enum.Enum):
    RED = 0
    BLUE = 1


@dataclasses.dataclass(frozen=True)
class Node:
    a: object
    b: object = None


def test_array_key_tells_dtype_shape_and_bytes_apart():
    x = np.arange(6, dtype=np.float32)
    assert array_key(x) == array_key(jnp.asarray(x)) == array_key(x.copy())
    assert array_key(x) != array_key(x.astype(np.float64))
    assert array_key(x) != array_key(x.reshape(2, 3))
    y = x.copy()
    y[3] = np.nextafter(y[3], np.float32(10))
    assert array_key(x) != array_key(y)
    assert array_key(np.float32(1.0)) == array_key(np.asarray(1.0, np.float32))
    assert array_key(x[::2]) == array_key(np.ascontiguousarray(x[::2]))  # a strided view: its values


def test_content_digest_is_equal_exactly_for_equal_contents():
    base = Node(a=(np.zeros(3), Colour.RED, 1.5), b={"k": [1, "s", b"raw"]})
    same = Node(a=(np.zeros(3), Colour.RED, 1.5), b={"k": [1, "s", b"raw"]})
    assert content_digest(base) == content_digest(same)
    variants = [
        Node(a=(np.zeros(3), Colour.BLUE, 1.5), b=base.b),  # an enum
        Node(a=(np.zeros(3, np.float32), Colour.RED, 1.5), b=base.b),  # a dtype
        Node(a=(np.zeros(3), Colour.RED, 1.5000001), b=base.b),  # a float
        Node(a=(np.zeros(3), Colour.RED, 1.5), b={"k": [1, "s", b"raw", None]}),  # a list's length
        Node(a=[np.zeros(3), Colour.RED, 1.5], b=base.b),  # a list instead of a tuple
        Node(a=(np.zeros(3), Colour.RED, 1), b=base.b),  # an int instead of a float
        Node(a=(np.zeros(3), Colour.RED, True), b=base.b),  # a bool instead of an int
    ]
    digests = {content_digest(v) for v in variants}
    assert len(digests) == len(variants) and content_digest(base) not in digests
    with pytest.raises(TypeError, match="object"):
        content_digest(Node(a=object()))


def test_models_are_keyed_on_their_bytes():
    m1 = mujoco.MjModel.from_xml_path(str(PLANAR))
    m2 = mujoco.MjModel.from_xml_path(str(PLANAR))
    assert np.array_equal(model_bytes(m1), model_bytes(m2)) and content_digest(m1) == content_digest(m2)
    m2.actuator_gear[0, 0] *= 2.0  # changed in place: another key
    assert content_digest(m1) != content_digest(m2)


def test_the_lru_forgets_the_least_recently_used_entry():
    cache = LruCache(2)
    cache.put("a", 1)
    cache.put("b", 2)
    assert cache.get("a") == 1  # "a" used: "b" is now the oldest
    cache.put("c", 3)
    assert "b" not in cache and cache.get("a") == 1 and cache.get("c") == 3 and len(cache) == 2
    assert cache.get("b", "missing") == "missing"
    cache.put("a", 10)  # an update is a use
    cache.put("d", 4)
    assert "c" not in cache and cache.get("a") == 10
    with pytest.raises(ValueError, match="size must be >= 1, got 0"):
        LruCache(0)
