"""The old path of :mod:`proprio_env.experiments.wrapper_fault_injection`, kept for
existing code: the same module object (attributes and monkeypatches are shared)."""

import sys

from proprio_env.experiments import wrapper_fault_injection as _moved

sys.modules[__name__] = _moved
