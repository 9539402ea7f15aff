"""The old path of :mod:`proprio_env.body.moment_arm_fitting`, kept for existing code: the same
module object (attributes and monkeypatches are shared)."""

import sys

from proprio_env.body import moment_arm_fitting as _moved

sys.modules[__name__] = _moved
