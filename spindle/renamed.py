"""The names classes had before the project spelled many-at-once one way (``Batch``).

Kept so that existing code still runs: reading an old name gives the renamed class with a
:class:`DeprecationWarning` naming the new one. Each module that renamed a class lists its
old names in a ``_RENAMED`` table and answers them from its module ``__getattr__``.
"""

from __future__ import annotations

import warnings
from typing import Any


def renamed_attribute(module: str, name: str, renamed: dict[str, str],
                      namespace: dict[str, Any]) -> Any:
    """``namespace[renamed[name]]`` with a DeprecationWarning, or the usual AttributeError."""
    if name not in renamed:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    new = renamed[name]
    warnings.warn(f"{module}.{name} is now called {new}", DeprecationWarning, stacklevel=3)
    return namespace[new]
