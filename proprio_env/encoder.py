"""The old path of :mod:`proprio_env.body.encoder`, kept for existing code: the same
module object (attributes and monkeypatches are shared)."""

import sys

from proprio_env.body import encoder as _moved

sys.modules[__name__] = _moved
