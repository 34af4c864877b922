"""Torque limits as acceleration limits (Del Prete 2018, Sec. IV, Alg. 4): ``import jaxlimits.torque``."""

from jaxlimits._src.torque import (
    TorqueBounds,
    acc_bounds_from_torque,
    box_scale,
    sample_states,
    torque_acc_box,
    torque_acc_box_conservative,
)
from jaxlimits._src.torque_box import TorqueBox

__all__ = [
    "TorqueBounds",
    "TorqueBox",
    "acc_bounds_from_torque",
    "box_scale",
    "sample_states",
    "torque_acc_box",
    "torque_acc_box_conservative",
]
