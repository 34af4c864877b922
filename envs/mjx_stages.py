"""MJX's stages, traced once per model: ``fwd_position(sys, d)`` and the others, with ``mujoco.mjx``'s signatures.

Tracing an MJX stage runs MJX's Python over every body level (a Panda's kinematics: ~1 s), and an env step is
traced again by every program that contains it (the training step, the evaluator, each test's rollout) and
holds several stages (a substep's, the observation's). Called with a concrete ``sys`` (the usual case: an env's
own model), each stage here runs MJX's Python once per model (per content: an env built again from the same
model, another test's or a vector env's copy, reuses it), argument shapes and trace context into a jaxpr
(without the arguments' shardings, which ``jax.jit``'s own cache keys on: an evaluator's sharded episodes traced
the Panda's position stage three more times), and calls a ``jax.jit`` of that jaxpr's evaluation. XLA inlines
the call. The results equal MJX's own stages bit for bit in the programs ``tests/test_mjx_stages.py`` checks; in a
whole evaluator episode XLA may fuse around the call differently (seen: 1 ulp of a return, as before this cache).
Measured on the motor Panda's vmapped step: 3.5 s → 0.25 s per trace after the first; a tiny-budget PPO run of the
Panda reach (``tests/test_panda_front_reach.py``; before and after side by side, one core each): 6 traces of the
position stage → 2, 90 s → 84 s.

With a traced ``sys`` (Brax's domain randomisation maps the env over a batch of models) there is nothing to
close over, and the stage is MJX's own, traced as before.

``brax_pipeline_init`` is a Brax ``PipelineEnv``'s reset physics (``pipeline_init``) with its ``mjx.forward`` traced
once per model the same way (``JointLimitShield`` installs it): the servo Panda's reset and two evaluators of its
env traced in 44.2 / 36.5 s instead of 58.5 / 62.8 s (alternating runs on one core beside a busy one).
"""

from __future__ import annotations

import functools
import types

import jax
import jax.extend
from mujoco import mjx

from jaxlimits.envs.content_cache import LruCache, content_digest
from jaxlimits.internal import is_traced

# (stage, the model's key) -> (sys, {signature: (jitted stage, output treedef)}); the key is the model's content
# (``content_digest``: envs built again from one model, a test's or a vector env's copies, share the traces, the
# jaxprs and so JAX's batching and lowering caches of them) or, for a model holding an object of unknown content,
# its identity (then ``sys`` is held so that its id cannot be reused while the entry lives). Bounded: a process
# that builds many envs (a campaign) keeps the most recent models'.
_TRACES = LruCache(64)
_MODEL_KEYS = LruCache(64)  # id(sys) -> (sys, key): each model object is digested once


def _model_key(sys):
    hit = _MODEL_KEYS.get(id(sys))
    if hit is not None and hit[0] is sys:
        return hit[1]
    try:
        key = ("content", content_digest(sys))
    except TypeError:
        key = ("id", id(sys))
    _MODEL_KEYS.put(id(sys), (sys, key))
    return key


def _signature(leaves) -> tuple:
    """What MJX's trace depends on: the leaves' shapes, dtypes and weak types; the configuration read while
    tracing (x64, rank and dtype promotion, matmul precision) and the abstract mesh (``pmap``'s or a sharded
    program's: the jaxpr's types name it). Not the leaves' shardings: an evaluator's inputs sharded over a mesh
    carry them in their types, and a trace keyed on them (``jax.jit``'s own) is redone for every variant
    (measured: three traces of a Panda's position stage in one evaluator)."""
    avals = tuple((a.shape, a.dtype, a.weak_type) for a in map(jax.typeof, leaves))
    c = jax.config
    return avals, (
        c.jax_enable_x64,
        c.jax_numpy_rank_promotion,
        c.jax_numpy_dtype_promotion,
        c.jax_default_matmul_precision,
        jax.sharding.get_abstract_mesh(),
    )


def _traces(stage, sys) -> dict | None:
    if any(is_traced(leaf) for leaf in jax.tree_util.tree_leaves(sys)):
        return None
    model_key = _model_key(sys)
    key = (stage, model_key)
    hit = _TRACES.get(key)
    if hit is not None and (model_key[0] == "content" or hit[0] is sys):
        return hit[1]
    traces = {}
    _TRACES.put(key, (sys, traces))
    return traces


def traced_once(stage):
    """``stage(sys, d)`` of ``mujoco.mjx``, its trace kept per concrete ``sys`` (see the module's docstring).

    MJX's Python runs once per model, ``d``'s shapes and trace context, into a jaxpr without shardings; a
    ``jax.jit`` of that jaxpr's evaluation is the call (re-binding a jaxpr is ~3x cheaper than tracing MJX, and
    JAX caches the jit's trace and its batching for inputs of the same types)."""

    @functools.wraps(stage)
    def call(sys, d):
        traces = _traces(stage, sys)
        if traces is None:
            return stage(sys, d)
        leaves, tree = jax.tree_util.tree_flatten(d)
        avals, config = _signature(leaves)
        key = (tree, avals, config)
        if key not in traces:
            plain = [jax.ShapeDtypeStruct(s, t, weak_type=w) for s, t, w in avals]
            closed, out = jax.make_jaxpr(functools.partial(stage, sys), return_shape=True)(
                jax.tree_util.tree_unflatten(tree, plain)
            )
            traces[key] = (jax.jit(jax.extend.core.jaxpr_as_fun(closed)), jax.tree_util.tree_structure(out))
        run, out_tree = traces[key]
        return jax.tree_util.tree_unflatten(out_tree, run(*leaves))

    return call


kinematics = traced_once(mjx.kinematics)
com_pos = traced_once(mjx.com_pos)
fwd_position = traced_once(mjx.fwd_position)
fwd_velocity = traced_once(mjx.fwd_velocity)
fwd_actuation = traced_once(mjx.fwd_actuation)
fwd_acceleration = traced_once(mjx.fwd_acceleration)
full_m = traced_once(mjx.full_m)
solve = traced_once(mjx.solve)
euler = traced_once(mjx.euler)
implicit = traced_once(mjx.implicit)
sensor_pos = traced_once(mjx.sensor_pos)
sensor_vel = traced_once(mjx.sensor_vel)
sensor_acc = traced_once(mjx.sensor_acc)
forward = traced_once(mjx.forward)


class _MjxWithStagedForward:
    """``mujoco.mjx`` with ``forward`` the one traced once per model (above)."""

    forward = staticmethod(forward)

    def __getattr__(self, name):
        return getattr(mjx, name)


def _with_staged_mjx(fn):
    """``fn`` (a function of a module that imports ``mujoco.mjx`` as ``mjx``) whose global ``mjx`` is
    ``_MjxWithStagedForward``: the same code object over a copy of its module's globals, so the module itself is
    never modified (thread-safe; a concurrent call of the module's own function keeps MJX's ``forward``)."""
    scope = dict(fn.__globals__, mjx=_MjxWithStagedForward())
    staged = types.FunctionType(fn.__code__, scope, fn.__name__, fn.__defaults__, fn.__closure__)
    staged.__kwdefaults__ = fn.__kwdefaults__
    return functools.wraps(fn)(staged)


def brax_pipeline_init(sys, q, qd, act=None, ctrl=None, debug: bool = False):
    """``brax.mjx.pipeline.init(sys, q, qd, act, ctrl, debug)`` (the reset physics of a Brax ``PipelineEnv`` on the
    mjx backend: ``make_data``, ``mjx.forward``, Brax's state layout) with its ``mjx.forward`` traced once per model.

    Brax's own function runs (its code object, so Brax's layout code is not copied), with its global ``mjx`` bound
    to ``_MjxWithStagedForward`` in a copy of its module's globals (Brax 0.14.2 reads ``mjx.forward`` from them
    when ``init`` runs); ``brax.mjx.pipeline`` itself is left as it is."""
    from brax.mjx import pipeline

    return _with_staged_mjx(pipeline.init)(sys, q, qd, act, ctrl, debug)
