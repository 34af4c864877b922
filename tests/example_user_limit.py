"""The user-written limit of ``docs/architecture.md``: a reduced-speed mode, registered as ``"half_speed"``.

Kept as a file so that the contract test (``test_limit_contract.py``) runs over it like over every
built-in family: a new entry of the registry is tested without editing the test.
"""

import jax.numpy as jnp

import jaxlimits as jl


class HalfSpeed(jl.Viability):
    """Del Prete's exact bounds, and ``|v| <= v_max / 2`` at the end of every step (a collaborative mode).

    Only the velocity term changes (the viability bounds' other terms do not involve ``v_max``), so the
    result is the exact viability bound for the halved speed limit.
    """

    def evaluate(self, q, v, a_prev=None):
        t = super().evaluate(q, v)
        a = jl.joint_arrays(q, v, self.limits)
        cap, T = 0.5 * a.v_max, self.model.period
        upper = {**t.upper, "half_speed": (cap - a.v) / T}
        lower = {**t.lower, "half_speed": (-cap - a.v) / T}
        return t._replace(upper=upper, lower=lower, viable=t.viable & (jnp.abs(a.v) <= cap))


jl.register_method("half_speed", HalfSpeed)
