"""MuJoCo-MJX / Brax robot-arm environments and the safety wrapper (installed as ``jaxlimits.envs``).

Importing this package sets the XLA CPU flags MJX needs (see ``jaxlimits._xla_flags``).
"""

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()
