"""The old path of :mod:`proprio_env.body.muscle_length`, kept for existing code: the same
module object (attributes and monkeypatches are shared)."""

import sys

from proprio_env.body import muscle_length as _moved

sys.modules[__name__] = _moved
