"""jaxlimits: exact, jit-compiled joint-limit bounds and projections for robot-arm RL in JAX.

The core (this package, without ``jaxlimits.envs``/``jaxlimits.training``) needs only jax and numpy.
"""

from jaxlimits._src.bounds import Bounds, acc_bounds, bound_terms, check_condition_11, is_viable
from jaxlimits._src.impact import ImpactJump, SpeedCap, equivalent_mass, impact_constraints, impact_jump, impact_speed_cap
from jaxlimits._src.integrate import Step, integrate_step
from jaxlimits._src.jerk import check_jerk_condition, is_viable_jerk
from jaxlimits._src.limits import JointLimits
from jaxlimits._src.qp import BoxQPResult, project_box, solve_box_qp
from jaxlimits._src.timescale import TimeScaleResult, fixed_time_ik, timescale_ik
from jaxlimits._src.torque import TorqueBounds, acc_bounds_from_torque, torque_acc_box, torque_acc_box_conservative

__version__ = "0.1.0"

__all__ = [
    "Bounds",
    "BoxQPResult",
    "ImpactJump",
    "JointLimits",
    "SpeedCap",
    "Step",
    "TimeScaleResult",
    "TorqueBounds",
    "acc_bounds",
    "acc_bounds_from_torque",
    "bound_terms",
    "check_condition_11",
    "check_jerk_condition",
    "equivalent_mass",
    "fixed_time_ik",
    "impact_constraints",
    "impact_jump",
    "impact_speed_cap",
    "integrate_step",
    "is_viable",
    "is_viable_jerk",
    "project_box",
    "solve_box_qp",
    "timescale_ik",
    "torque_acc_box",
    "torque_acc_box_conservative",
]
