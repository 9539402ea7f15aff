"""The old path of :mod:`proprio_env.training.sb3`, kept for existing code: the same
module object (attributes and monkeypatches are shared)."""

import sys

from proprio_env.training import sb3 as _moved

sys.modules[__name__] = _moved
