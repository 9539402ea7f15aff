"""The one table of backends and the one rule that resolves a user's ``backend=``.

Every entry point that has a numpy and a C implementation (``spindle.simulate``, the chains,
the spindle banks, the envs, the wrappers, training, the scripts) takes
``backend="numpy" | "c" | "auto"`` with the one default :data:`DEFAULT_BACKEND` (``"auto"``),
resolves it here once with :func:`resolve_backend`, and stores and reports the resolved name
(``.backend``), never ``"auto"``.

This module imports no C: ``"auto"`` loads :mod:`spindle.native.build` only to ask whether
the library can be used.
"""

from __future__ import annotations

import os
from functools import cache

BACKENDS = ("numpy", "c")
"""The implementations: ``"numpy"`` (the readable reference) and ``"c"``
(``spindle/native/c/``, compiled on first use: the same API, outputs and counters)."""
BACKEND_CHOICES = (*BACKENDS, "auto")
"""What every ``backend=`` accepts: one of :data:`BACKENDS`, or ``"auto"`` (C where the
library loads or builds here, else numpy)."""
DEFAULT_BACKEND = "auto"
"""The one default of every ``backend=`` argument."""


def resolve_backend(name: str = DEFAULT_BACKEND) -> str:
    """The backend ``name`` selects: ``"numpy"`` or ``"c"``.

    ``"auto"`` is ``"c"`` when the native library can be used here: a valid cached build (see
    :mod:`spindle.native.build`), or a C compiler that builds it now (once: the build is
    cached and every C object loads that same library); otherwise ``"numpy"``. It never
    raises for a missing or failing compiler, a damaged cache or a library that does not
    load: each falls back to numpy.

    Raises:
        ValueError: ``name`` is not one of :data:`BACKEND_CHOICES`.
    """
    if not isinstance(name, str) or name not in BACKEND_CHOICES:
        raise ValueError(f"backend={name!r} is not one of {BACKEND_CHOICES}")
    if name != "auto":
        return name
    usable = _native_usable(os.environ.get("CC", ""), os.environ.get("PROPRIO_C_CACHE", ""))
    return "c" if usable else "numpy"


@cache
def _native_usable(cc: str, cache_dir: str) -> bool:
    """Whether the C library loads (built first if need be) with this $CC and cache: a
    failing build is tried once per setting, not at every object built."""
    del cc, cache_dir  # the cache key: what the build reads from the environment
    try:
        # imported here so that numpy-only use never loads ctypes or the C build
        from spindle.native.build import load

        load("double")
    except Exception:  # any reason the library cannot be used means numpy
        return False
    return True
