"""``jaxlimits.internal.batched_like``: a scan carry batched from the start batches the scan's body once under
``vmap``, with the values unchanged (the Brax shield's substep scan uses it)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxlimits.internal import batched_like


def _scan(x, make_batched: bool):
    """A scan whose carry starts as constants (unbatched under vmap) and picks up ``x`` in its body."""

    def body(carry, t):
        acc, count, flag = carry
        return (acc + x * t, count + 1, flag | (x > 2.0)), acc

    init = (jnp.zeros((), x.dtype), jnp.zeros((), jnp.int32), jnp.zeros((), bool))
    if make_batched:
        init = batched_like(init, x)
    return jax.lax.scan(body, init, jnp.arange(4.0, dtype=x.dtype))


@pytest.mark.parametrize("make_batched", [False, True], ids=["constant_carry", "batched_like"])
def test_the_body_is_batched_once_and_the_values_do_not_change(make_batched, monkeypatch):
    # JAX's scan batching rule batches the body's jaxpr once per round of its carry fixpoint; the rounds are counted
    # at the (private) function it calls, the only place they show
    from jax._src.lax.control_flow import loops

    rounds, batch_jaxpr = [], loops.batching.batch_jaxpr
    monkeypatch.setattr(loops.batching, "batch_jaxpr", lambda *a, **k: rounds.append(1) or batch_jaxpr(*a, **k))
    xs = jnp.asarray([0.5, 1.5, 3.0], jnp.float32)
    out = jax.jit(jax.vmap(lambda x: _scan(x, make_batched)))(xs)
    assert len(rounds) == (1 if make_batched else 2), len(rounds)
    loop = [_scan(x, False) for x in xs]
    for got, want in zip(jax.tree.leaves(out), zip(*[jax.tree.leaves(r) for r in loop])):
        np.testing.assert_array_equal(np.asarray(got), np.stack([np.asarray(w) for w in want]))


def test_outside_vmap_and_for_keys_nothing_changes():
    key = jax.random.key(0)
    tree = {"a": jnp.arange(3.0), "b": jnp.int32(7), "k": key}
    out = jax.jit(lambda t: batched_like(t, jnp.float32(1.0)))(tree)
    np.testing.assert_array_equal(out["a"], tree["a"])
    assert out["b"] == 7 and out["b"].dtype == jnp.int32
    assert jnp.array_equal(jax.random.key_data(out["k"]), jax.random.key_data(key))
    # NaN or inf in the reference does not reach the values
    out = jax.vmap(lambda r: batched_like(jnp.ones(2), r))(jnp.asarray([jnp.nan, jnp.inf]))
    np.testing.assert_array_equal(out, np.ones((2, 2)))
