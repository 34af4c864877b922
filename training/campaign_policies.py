"""The safety campaign's policy classes (``jaxlimits campaign``): scripted toward-limit, bang-bang and random
policies (``evaluate.scripted_policy``), random walks in command space, NaN bursts, and a trained policy with
noise, as one ``(params, obs, key, t)`` policy that ``params["kind"]`` switches between (one compilation for
every class). Shared by the Brax rows (``campaign``) and the Gymnasium rows (``campaign_gym``)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from jaxlimits.training import evaluate

POLICY_CLASSES = ("toward_limit", "bang_bang", "random", "random_walk", "nan_burst")
TRAINED = "trained_noisy"
WALK_STEP = 0.1  # random_walk: standard deviation of one step's increment [normalised action units]
BAD_VALUES = (jnp.nan, jnp.inf, -jnp.inf, 1e30)  # what nan_burst puts into an action


def _reflect(x):
    """``x`` folded into ``[-1, 1]`` by reflection at the bounds (a triangle wave of period 4)."""
    y = jnp.mod(x + 1.0, 4.0)
    return jnp.where(y <= 2.0, y - 1.0, 3.0 - y)


def random_walk_policy(n: int, horizon: int, step: float = WALK_STEP):
    """A random walk in command space ``(params, obs, key, t) -> action (n,)``: start uniform in ``[-1, 1]``,
    Gaussian increments of standard deviation ``step``, reflected at ``±1``. Stateless (the evaluator's
    policies are): the walk's ``horizon`` increments are drawn from the episode key and summed up to ``t``."""

    def policy(params, obs, key, t):
        del params, obs
        k_start, k_inc = jax.random.split(jax.random.fold_in(key[0], 1))
        start = jax.random.uniform(k_start, (n,), jnp.float32, -1.0, 1.0)
        inc = step * jax.random.normal(k_inc, (horizon, n), jnp.float32)
        taken = (jnp.arange(horizon) < t)[:, None]
        return _reflect(start + jnp.sum(jnp.where(taken, inc, 0.0), axis=0))

    return policy


def nan_burst_policy(n: int):
    """Uniform actions in ``[-1, 1]`` with bursts of non-finite or absurd entries: in every period of 10-40 steps
    (drawn per episode) the first 1-5 steps carry, in each joint with probability 1/2, one of NaN, +inf, -inf,
    1e30 (``BAD_VALUES``; at least one joint per burst step)."""
    bad_values = jnp.asarray(BAD_VALUES, jnp.float32)

    def policy(params, obs, key, t):
        del params, obs
        k_per, k_len = jax.random.split(jax.random.fold_in(key[0], 2))
        period = jax.random.randint(k_per, (), 10, 41)
        length = jax.random.randint(k_len, (), 1, 6)
        k_act, k_mask, k_val = jax.random.split(jax.random.fold_in(key[1], t), 3)
        action = jax.random.uniform(k_act, (n,), jnp.float32, -1.0, 1.0)
        mask = jax.random.bernoulli(k_mask, 0.5, (n,)).at[0].set(True)
        mask = jax.random.permutation(jax.random.fold_in(k_mask, 1), mask)
        bad = bad_values[jax.random.randint(k_val, (n,), 0, len(BAD_VALUES))]
        return jnp.where(mask & (t % period < length), bad, action)

    return policy


def campaign_policy(n: int, horizon: int, trained: Callable | None = None, noise: float = 0.3):
    """One policy ``(params, obs, key, t)`` for every class: ``params["kind"]`` (int32 scalar) indexes
    ``classes``; ``params["net"]`` are ``trained``'s parameters when it is given. Returns
    ``(policy, classes)``."""
    scripted = [evaluate.scripted_policy(k, n) for k in evaluate.SCRIPTED]
    branches = scripted + [random_walk_policy(n, horizon), nan_burst_policy(n)]
    classes = POLICY_CLASSES
    if trained is not None:

        def noisy(params, obs, key, t):
            a = trained(params["net"], obs, key, t)
            return a + noise * jax.random.normal(jax.random.fold_in(key[1], t), a.shape, a.dtype)

        branches.append(noisy)
        classes = classes + (TRAINED,)

    def policy(params, obs, key, t):
        fns = [lambda p, o, k, s, f=f: jnp.asarray(f(p, o, k, s), jnp.float32) for f in branches]
        return jax.lax.switch(params["kind"], fns, params, obs, key, t)

    return policy, classes
