"""The old path of :mod:`spindle.chain.driver`, kept for existing code: the same module object
(attributes and monkeypatches are shared)."""

import sys

from spindle.chain import driver as _moved

sys.modules[__name__] = _moved
