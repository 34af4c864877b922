"""The impact-aware speed cap (Wang & Kheddar 2019) as an acceleration limit: one halfspace row.

The cap is the largest contact-normal approach speed whose predicted joint-velocity jumps and
impulsive torques keep (16), (17) and (20) (``impact.impact_speed_cap``); imposed on the velocity at
the end of the step it is the row ``J^T n . (v + a dt) <= margin * cap`` (``speed_cap_halfspace``).
It is not a box per joint: its box is unbounded and the row travels in ``Constraint.G``/``Constraint.h``
(``ImpactCap.constraint``; ``bounds`` refuses, since a box alone would drop the row).
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxlimits._src.impact import DEFAULT_REG, impact_speed_cap, speed_cap_halfspace
from jaxlimits._src.impact_contact import PAPER, check_contact
from jaxlimits._src.limit import AccelerationLimit, Terms


class ImpactCap(AccelerationLimit):
    """Speed cap at one state (or a batch): ``M`` (..., n, n), ``J`` (..., 3, n), ``normal`` (..., 3).

    ``limits`` (``q_min``, ``q_max``, ``v_max``), ``tau_imp_max`` [N m], ``dt`` [s], ``c_max``,
    ``dt_impact`` [s] and ``reg`` as in ``impact_speed_cap``; ``margin`` in ``(0, 1]`` scales the cap;
    ``v_pre_range``: optional ``(v_lo, v_hi)``, the box the pre-impact velocity lies in (e.g.
    ``v + dt [lower, upper]`` of the other limits' bounds); ``contact``: the contact model
    (``PaperContact()`` or ``CoulombContact(mu)``, see ``impact_contact``). ``viable``: ``cap > 0`` (some approach
    speed is safe). ``cap(q, v)`` gives the cap itself [m/s], shape ``(...)``.
    """

    has_rows = True

    def __init__(
        self,
        M,
        J,
        normal,
        limits,
        tau_imp_max,
        dt,
        c_max,
        dt_impact,
        reg=DEFAULT_REG,
        margin=1.0,
        v_pre_range=None,
        contact=PAPER,
    ):
        if not 0.0 < float(margin) <= 1.0:
            raise ValueError(f"ImpactCap: margin must be in (0, 1], got {margin!r}")
        self.M, self.J, self.normal, self.limits = M, J, normal, limits
        self.tau_imp_max, self.dt, self.c_max, self.dt_impact = tau_imp_max, dt, c_max, dt_impact
        self.reg, self.margin, self.v_pre_range = reg, margin, v_pre_range
        self.contact = check_contact(contact)

    def cap(self, q, v):
        c = impact_speed_cap(
            self.M,
            self.J,
            self.normal,
            q,
            v,
            self.limits,
            self.tau_imp_max,
            self.dt,
            self.c_max,
            self.dt_impact,
            self.reg,
            v_pre_range=self.v_pre_range,
            contact=self.contact,
        ).cap
        return c * self.margin

    def evaluate(self, q, v, a_prev=None) -> Terms:
        cap = self.cap(q, v)
        G, h = speed_cap_halfspace(self.M, self.J, self.normal, v, cap, self.dt)
        big = jnp.full(G.shape[:-2] + G.shape[-1:], jnp.inf, G.dtype)
        viable = jnp.broadcast_to((cap > 0)[..., None], big.shape)
        return Terms({"acceleration": big}, {"acceleration": -big}, viable, jnp.zeros(big.shape, bool), G, h)
