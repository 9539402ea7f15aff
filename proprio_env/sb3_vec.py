"""The old path of :mod:`proprio_env.training.sb3_vec`, kept for existing code: the same
module object (attributes and monkeypatches are shared)."""

import sys

from proprio_env.training import sb3_vec as _moved

sys.modules[__name__] = _moved
