"""``NonFiniteActionGuard``: a policy's NaN/inf action never reaches the env (Brax; one wrapper, one job).

    env = NonFiniteActionGuard(JointLimitShield(brax.envs.get_environment("pusher", backend="mjx"), v_max=2.0))

A shield alone keeps a NaN out of the *simulator* (it brakes on a non-finite ``ctrl``), but the env's own
``step`` still computes its reward and observation from the action (Brax ``pusher``'s control cost is
``sum(action^2)``): one NaN action then poisons a training batch. The guard, outermost, checks the action
(``(..., action_size)``): where an entry is NaN/inf (or ``|x| > 1e10``, MuJoCo's bound on a valid ctrl) the
*whole* action is replaced by zeros before the env sees it, and ``state.info[FLAG]`` is set for that step,
so that a ``JointLimitShield`` inside substitutes the safe braking action for the zeros (counted in
``shield/nonfinite``). Without a shield inside, zeros are what the env gets (its neutral command: no torque
for a motor, the middle of the range for a servo). Per step ``state.metrics["nonfinite_action"]`` is 1.0
where the action was replaced.
"""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import mujoco

with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    from brax.envs.base import State, Wrapper

FLAG = "nonfinite_action"  # state.info key: this step's action was replaced (a shield inside brakes)
MAX_ACTION = mujoco.mjMAXVAL  # 1e10: a larger |ctrl| is rejected by MuJoCo itself


def bad_action(action: jax.Array) -> jax.Array:
    """``(...)`` bool: some entry of ``action`` ``(..., k)`` is NaN, inf or larger than ``MAX_ACTION``."""
    return ~jnp.all(jnp.abs(action) <= MAX_ACTION, axis=-1)


class NonFiniteActionGuard(Wrapper):
    """Replace a non-finite action by zeros before the wrapped env's ``step``; see the module docstring.

    Brax's ``DomainRandomizationVmapWrapper`` (its trainers' ``randomization_fn``) calls the innermost env's
    ``step``/``reset`` directly, past every wrapper in between, this one too: so the guard also wraps the innermost
    env's ``step``/``reset`` (instance attributes around whatever was there, e.g. a ``JointLimitShield``'s), which
    act only when this wrapper's own ``step`` was bypassed (``_active``: set while it runs, at trace time). One
    guard per env (a second one raises)."""

    def __init__(self, env):
        super().__init__(env)
        base = env.unwrapped
        if "_guarded_by" in vars(base):
            raise ValueError("this env already has a NonFiniteActionGuard (one per env)")
        base._guarded_by = self
        self._active = False
        self._env_step, self._env_reset = base.step, base.reset
        base.step, base.reset = self._innermost_step, self._innermost_reset

    @staticmethod
    def _flagged(state: State) -> State:
        flag = jnp.zeros(state.reward.shape, bool)
        return state.replace(info={**state.info, FLAG: flag}, metrics={**state.metrics, FLAG: flag.astype(jnp.float32)})

    def reset(self, rng: jax.Array) -> State:
        return self._flagged(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        self._active = True
        try:
            return self._guard(self.env.step, state, action)
        finally:
            self._active = False

    def _innermost_reset(self, rng: jax.Array) -> State:
        return self._flagged(self._env_reset(rng))

    def _innermost_step(self, state: State, action: jax.Array) -> State:
        if self._active:  # reached through this wrapper's own step: the action is already clean
            return self._env_step(state, action)
        return self._guard(self._env_step, state, action)

    @staticmethod
    def _guard(step, state: State, action: jax.Array) -> State:
        bad = bad_action(action)
        clean = jnp.where(bad[..., None], jnp.zeros_like(action), action)
        nstate = step(state.replace(info={**state.info, FLAG: bad}), clean)
        return nstate.replace(
            info={**nstate.info, FLAG: bad}, metrics={**nstate.metrics, FLAG: bad.astype(jnp.float32)}
        )
