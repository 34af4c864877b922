"""Impact-aware bounds (Wang & Kheddar 2019): ``import jaxlimits.impact`` (see ``docs/impact.md``)."""

from jaxlimits._src.impact import (
    DEFAULT_REG,
    ImpactJump,
    SpeedCap,
    check_restitution,
    equivalent_mass,
    impact_constraints,
    impact_jump,
    impact_speed_cap,
    speed_cap_halfspace,
)
from jaxlimits._src.impact_contact import ContactModel, CoulombContact, PaperContact, UnitJumps, check_contact

__all__ = [
    "ContactModel",
    "CoulombContact",
    "PaperContact",
    "UnitJumps",
    "DEFAULT_REG",
    "ImpactJump",
    "SpeedCap",
    "check_contact",
    "check_restitution",
    "equivalent_mass",
    "impact_constraints",
    "impact_jump",
    "impact_speed_cap",
    "speed_cap_halfspace",
]
