"""MJX's stages, traced once per model: ``fwd_position(sys, d)`` and the others, with ``mujoco.mjx``'s signatures.

Tracing an MJX stage runs MJX's Python over every body level (a Panda's kinematics: ~1 s), and an env step is
traced again by every program that contains it (the training step, the evaluator, each test's rollout) and
holds several stages (a substep's, the observation's). Called with a concrete ``sys`` (the usual case: an env's
own model), each stage here is a ``jax.jit`` of the stage with ``sys`` closed over, kept per model: JAX reuses a
jitted function's trace for the same argument shapes, so MJX's Python runs once per model and shape, and XLA
inlines the call, so the compiled program and its results are the same. Measured on the motor Panda's
vmapped step: 3.5 s → 0.25 s per trace after the first; ``tests/test_mjx_stages.py`` checks the equality.

With a traced ``sys`` (Brax's domain randomisation maps the env over a batch of models) there is nothing to
close over, and the stage is MJX's own, traced as before.
"""

from __future__ import annotations

import collections
import functools

import jax
from mujoco import mjx

from jaxlimits.internal import is_traced

# (stage, id(sys)) -> (sys, jitted stage); ``sys`` is held so that its id cannot be reused while its entry
# lives. Bounded: a process that builds many envs (a campaign) keeps the most recent models' traces.
_JITTED: collections.OrderedDict = collections.OrderedDict()
_MAX_MODELS = 64


def _jitted(stage, sys):
    key = (stage, id(sys))
    hit = _JITTED.get(key)
    if hit is not None and hit[0] is sys:
        _JITTED.move_to_end(key)
        return hit[1]
    if any(is_traced(leaf) for leaf in jax.tree_util.tree_leaves(sys)):
        return None
    jitted = jax.jit(functools.partial(stage, sys))
    _JITTED[key] = (sys, jitted)
    if len(_JITTED) > _MAX_MODELS:
        _JITTED.popitem(last=False)
    return jitted


def traced_once(stage):
    """``stage(sys, d)`` of ``mujoco.mjx``, its trace kept per concrete ``sys`` (see the module's docstring)."""

    @functools.wraps(stage)
    def call(sys, d):
        jitted = _jitted(stage, sys)
        return stage(sys, d) if jitted is None else jitted(d)

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
