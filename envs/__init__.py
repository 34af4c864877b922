"""MuJoCo-MJX / Brax robot-arm environments and the safety wrapper (installed as ``jaxlimits.envs``).

Importing this package sets the XLA CPU flags MJX needs (see ``jaxlimits._xla_flags``).
"""

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()

# Public names, imported lazily so that ``import jaxlimits.envs`` (done early for the XLA flags)
# does not load MuJoCo and Brax until an env is used.
_EXPORTS = {
    "ArmReach": "jaxlimits.envs.arm",
    "VIOLATION_KEYS": "jaxlimits.envs.arm",
    "make_panda_reach": "jaxlimits.envs.arm",
    "make_panda_front_reach": "jaxlimits.envs.arm",
    "make_planar_reach": "jaxlimits.envs.arm",
    "SafetyWrapper": "jaxlimits.envs.safety",
    "JointLimitShield": "jaxlimits.envs.brax_shield",
    "ImpactPoint": "jaxlimits.envs.impact_point",
    "NonFiniteActionGuard": "jaxlimits.envs.nonfinite_guard",
    "Robot": "jaxlimits.envs.robot",
    "Reach": "jaxlimits.envs.reach",
    "make_servo_panda_reach": "jaxlimits.envs.reach",
    "make_servo_panda_front_reach": "jaxlimits.envs.reach",
    "make_planar_robot_reach": "jaxlimits.envs.reach",
    "AccelerationActions": "jaxlimits.envs.acceleration_actions",
    "ViolationMetrics": "jaxlimits.envs.violation_metrics",
    "make_ur5e_reach": "jaxlimits.envs.reach",
    "shield_rollout": "jaxlimits.envs.adversarial",
    "adversarial_rollout": "jaxlimits.envs.adversarial",
    "TaskSpaceActions": "jaxlimits.envs.task_space",
    "WallStrike": "jaxlimits.envs.wall_strike",
    "make_wall_strike": "jaxlimits.envs.wall_strike",
    "make_planar_wall_strike": "jaxlimits.envs.wall_strike",
    "Strike": "jaxlimits.envs.strike",
    "strike_point": "jaxlimits.envs.strike",
    "make_planar_robot_wall": "jaxlimits.envs.strike",
    "ArmEnv": "jaxlimits.envs.gym",
    "ArmVectorEnv": "jaxlimits.envs.gym",
    "register_envs": "jaxlimits.envs.gym",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'jaxlimits.envs' has no attribute {name!r}")


def _default_headless_gl():
    """Headless rendering by default: MUJOCO_GL=egl when unset and there is no display (read by MuJoCo at import)."""
    import os

    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["MUJOCO_GL"] = "egl"


_default_headless_gl()
