"""jaxlimits: exact, jit-compiled joint-limit bounds and projections for robot-arm RL in JAX.

The core (this package, without ``jaxlimits.envs``/``jaxlimits.training``) needs only jax and numpy.
"""

from jaxlimits._src.bounds import Bounds, acc_bounds, bound_terms, check_condition_11, is_viable
from jaxlimits._src.integrate import Step, integrate_step
from jaxlimits._src.limits import JointLimits

__version__ = "0.1.0"

__all__ = [
    "Bounds",
    "JointLimits",
    "Step",
    "acc_bounds",
    "bound_terms",
    "check_condition_11",
    "integrate_step",
    "is_viable",
]
