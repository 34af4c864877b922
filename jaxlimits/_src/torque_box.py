"""The torque box as an acceleration limit: every acceleration inside it needs at most ``tau_max``.

``[-s a_nominal, s a_nominal]`` with ``s = clip(box_scale(M, h, tau_max, a_nominal), 0, 1)`` (Del Prete
2018, Sec. IV; ``torque.box_scale``): the largest box of that shape whose every point satisfies
``|M a + h| <= tau_max`` at this state. ``M`` and ``h`` come from the simulator (``jaxlimits.envs``
uses MJX), so this module needs no dynamics library.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits._src.limit import AccelerationLimit, Terms
from jaxlimits._src.torque import box_scale


class TorqueBox(AccelerationLimit):
    """Torque-feasible box at one state (or a batch).

    Args:
      M: ``(..., n, n)`` joint-space inertia [kg m^2]; h: ``(..., n)`` bias forces (gravity, Coriolis,
        damping) [N m], both at the state the bounds are for; tau_max: ``(n,)`` or scalar [N m], > 0;
      a_nominal: ``(n,)`` or scalar [rad/s^2], the box's shape (e.g. ``JointLimits.a_max``).

    ``evaluate`` ignores ``q``/``v`` (the state is in ``M`` and ``h``); its only term is
    ``"acceleration"``. ``viable``: ``box_scale > 0`` (gravity and Coriolis alone leave torque to
    spare; else the box is ``{0}`` and not even that is realisable).
    """

    def __init__(self, M, h, tau_max, a_nominal):
        self.M, self.h = jnp.asarray(M), jnp.asarray(h)
        self.tau_max, self.a_nominal = tau_max, a_nominal

    def scale(self):
        """``(...)``: the unclipped ``box_scale`` (``<= 0``: no torque to spare)."""
        return box_scale(self.M, self.h, self.tau_max, self.a_nominal)

    def evaluate(self, q=None, v=None, a_prev=None) -> Terms:
        s = self.scale()
        a_nom = jnp.broadcast_to(jnp.asarray(self.a_nominal, self.h.dtype), self.h.shape)
        hi = jnp.clip(s, 0.0, 1.0)[..., None] * a_nom
        viable = jnp.broadcast_to((s > 0)[..., None], hi.shape)
        return Terms({"acceleration": hi}, {"acceleration": -hi}, viable, jnp.zeros(hi.shape, bool))
