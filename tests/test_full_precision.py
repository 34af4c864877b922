"""The envs' physics and the shields' decisions trace every float32 matrix product at full float32
precision (``envs/arm._mjx_tracing``). On a GPU JAX's default is TF32: measured on an H200, the servo
Panda's realised acceleration missed the commanded one by up to 0.14 rad/s^2 and a PPO run had 55
position-violating steps. A CPU cannot show TF32, so this checks the traced programs themselves: every
``dot_general`` in them, at every depth (scans, conds, custom rules), asks for ``HIGHEST``."""

from __future__ import annotations

import jaxlimits.envs  # noqa: F401  (XLA flags first)

import jax
import jax.numpy as jnp
import pytest
from jax.extend import core as jcore

from jaxlimits.envs import JointLimitShield, SafetyWrapper
from jaxlimits.envs.arm import ASSETS, make_planar_reach
from jaxlimits.envs.reach import Reach


def _dot_precisions(jaxpr) -> list:
    """The ``precision`` of every ``dot_general`` in ``jaxpr`` and the jaxprs nested in its equations."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            out.append(eqn.params["precision"])
        for p in eqn.params.values():
            for sub in p if isinstance(p, (tuple, list)) else (p,):
                if isinstance(sub, jcore.ClosedJaxpr):
                    out += _dot_precisions(sub.jaxpr)
                elif isinstance(sub, jcore.Jaxpr):
                    out += _dot_precisions(sub)
    return out


def _assert_all_highest(fn, *args):
    precisions = _dot_precisions(jax.make_jaxpr(fn)(*args).jaxpr)
    assert len(precisions) >= 5  # the mass matrix products, the solves' updates, ...
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert all(p == highest for p in precisions), sorted({str(p) for p in precisions})


@pytest.mark.parametrize("torque_box", [False, True])
def test_safety_wrapper_step_traces_full_float32_products(torque_box):
    env = SafetyWrapper(make_planar_reach(), torque_box=torque_box)
    state = env.reset(jax.random.PRNGKey(0))
    _assert_all_highest(env.step, state, jnp.full(3, 0.5, jnp.float32))


def test_joint_limit_shield_step_traces_full_float32_products():
    env = JointLimitShield(Reach(ASSETS / "planar3.xml"))
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    _assert_all_highest(env.step, state, jnp.full(3, 0.5, jnp.float32))
