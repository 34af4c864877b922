"""jaxlimits: exact, jit-compiled joint-limit bounds and projections for robot-arm RL in JAX.

The core (this package, without ``jaxlimits.envs``/``jaxlimits.training``) needs only jax and numpy.
"""

from jaxlimits._src.bounds import acc_bounds, bound_terms, is_viable, is_viable_jerk
from jaxlimits._src.compose import Intersection, intersect
from jaxlimits._src.discretisation import INTEGRATORS, make_discretisation
from jaxlimits._src.impact import (
    ImpactJump,
    SpeedCap,
    equivalent_mass,
    impact_constraints,
    impact_jump,
    impact_speed_cap,
)
from jaxlimits._src.impact_cap import ImpactCap
from jaxlimits._src.impact_contact import ContactModel, CoulombContact, PaperContact
from jaxlimits._src.integrate import Step, integrate_step
from jaxlimits._src.jerk import Jerk
from jaxlimits._src.jerk_condition import check_jerk_condition
from jaxlimits._src.jerk_paper import JerkPaper
from jaxlimits._src.limit import AccelerationLimit, Bounds, Constraint, Terms, brake_on_conflict
from jaxlimits._src.joint_state import JointArrays, joint_arrays
from jaxlimits._src.limits import JointLimits
from jaxlimits._src.naive import Naive
from jaxlimits._src.qp import GRADIENTS as PROJECTION_GRADIENTS
from jaxlimits._src.qp import BoxQPResult, project_box, solve_box_qp
from jaxlimits._src.registry import METHODS, make_limit, register_method
from jaxlimits._src.semi_implicit import SemiImplicit
from jaxlimits._src.timescale import TimeScaleResult, fixed_time_ik, timescale_ik
from jaxlimits._src.torque import TorqueBounds, acc_bounds_from_torque, torque_acc_box, torque_acc_box_conservative
from jaxlimits._src.torque_box import TorqueBox
from jaxlimits._src.viability import check_condition_11, Viability
from jaxlimits._src.zoh import ZeroOrderHold

__version__ = "0.1.0"

__all__ = [
    "AccelerationLimit",
    "Bounds",
    "BoxQPResult",
    "Constraint",
    "ContactModel",
    "CoulombContact",
    "INTEGRATORS",
    "ImpactCap",
    "ImpactJump",
    "Intersection",
    "Jerk",
    "JerkPaper",
    "JointArrays",
    "JointLimits",
    "METHODS",
    "Naive",
    "PROJECTION_GRADIENTS",
    "SemiImplicit",
    "PaperContact",
    "SpeedCap",
    "Step",
    "Terms",
    "TimeScaleResult",
    "TorqueBounds",
    "TorqueBox",
    "Viability",
    "ZeroOrderHold",
    "acc_bounds",
    "acc_bounds_from_torque",
    "bound_terms",
    "brake_on_conflict",
    "check_condition_11",
    "check_jerk_condition",
    "equivalent_mass",
    "fixed_time_ik",
    "impact_constraints",
    "impact_jump",
    "impact_speed_cap",
    "integrate_step",
    "intersect",
    "is_viable",
    "is_viable_jerk",
    "joint_arrays",
    "make_discretisation",
    "make_limit",
    "project_box",
    "register_method",
    "solve_box_qp",
    "timescale_ik",
    "torque_acc_box",
    "torque_acc_box_conservative",
]
