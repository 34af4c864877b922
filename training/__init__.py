"""Training, evaluation and the command-line entry point (installed as ``jaxlimits.training``).

Importing this package sets the XLA CPU flags MJX needs (see ``jaxlimits._xla_flags``).
"""

from jaxlimits._xla_flags import set_cpu_xla_flags

set_cpu_xla_flags()
