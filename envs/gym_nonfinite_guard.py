"""``NonFiniteActionGuardWrapper``: a policy's NaN/inf action never reaches a Gymnasium env (one wrapper, one job).

    env = NonFiniteActionGuardWrapper(JointLimitShieldWrapper(gymnasium.make("Pusher-v5"), v_max=2.0))

The Gymnasium counterpart of ``nonfinite_guard.NonFiniteActionGuard``: a shield keeps a NaN out of MuJoCo,
but the env's own ``step`` computes its reward from the action (``Pusher-v5``'s control cost is
``sum(action^2)``), so a NaN action gives a NaN reward. The guard, outside, replaces an action with a NaN/inf
entry (or ``|x| > 1e10``, MuJoCo's bound on a valid ctrl) by zeros, whole, before the env sees it; a
``JointLimitShieldWrapper`` on the same env is told (``brake_on_next_step``) and substitutes the safe
braking action for the zeros (its ``info["shield"]["nonfinite"]``). Without a shield, zeros are what the
env gets. ``info["nonfinite_action"]``: this step's action was replaced; ``replaced``: how many so far.
"""

from __future__ import annotations

import gymnasium
import numpy as np

from jaxlimits.envs.gym_shield import MJ_MAXVAL


class NonFiniteActionGuardWrapper(gymnasium.Wrapper, gymnasium.utils.RecordConstructorArgs):
    """Replace a non-finite action by zeros before the wrapped env's ``step``; see the module docstring.
    Recorded in ``env.spec`` (``gymnasium.make(env.spec)`` rebuilds the stack)."""

    def __init__(self, env: gymnasium.Env):
        gymnasium.utils.RecordConstructorArgs.__init__(self)
        gymnasium.Wrapper.__init__(self, env)
        self.replaced = 0

    def step(self, action):
        a = np.asarray(action)
        bad = not bool(np.all(np.abs(a) <= MJ_MAXVAL))
        if bad:
            a = np.zeros(a.shape, a.dtype if np.issubdtype(a.dtype, np.floating) else np.float64)
            self.replaced += 1
            shield = vars(self.env.unwrapped).get("_shielded_by")
            if shield is not None:
                shield.brake_on_next_step()
        obs, reward, terminated, truncated, info = self.env.step(a)
        info = dict(info)
        info["nonfinite_action"] = bad
        return obs, reward, terminated, truncated, info
