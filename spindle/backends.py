"""The one table of backends and the one rule that resolves a user's ``backend=``.

Every entry point that has a numpy and a C implementation (``spindle.simulate``, the chains,
the spindle banks, the envs, the wrappers, training, the scripts) takes
``backend="numpy" | "c" | "auto"`` with the one default :data:`DEFAULT_BACKEND` (``"auto"``),
resolves it here once with :func:`resolve_backend`, and stores and reports the resolved name
(``.backend``), never ``"auto"``.

:data:`IMPLEMENTATIONS` is the one table of what each backend of each component is, by import
path; :func:`implementation` resolves a ``backend=`` and imports the class or function it
names. So no module of the numpy rooms imports the C port: the receptor models, the chain and
the stimulator name their C twins here, and :mod:`spindle.native` is loaded only when a
backend resolves to ``"c"``. This module imports no C itself: ``"auto"`` loads
:mod:`spindle.native.build` only to ask whether the library can be used.
"""

from __future__ import annotations

import importlib
import os
from functools import cache
from typing import Any

BACKENDS = ("numpy", "c")
"""The implementations: ``"numpy"`` (the readable reference) and ``"c"``
(``spindle/native/c/``, compiled on first use: the same API, outputs and counters)."""
BACKEND_CHOICES = (*BACKENDS, "auto")
"""What every ``backend=`` accepts: one of :data:`BACKENDS`, or ``"auto"`` (C where the
library loads or builds here, else numpy)."""
DEFAULT_BACKEND = "auto"
"""The one default of every ``backend=`` argument."""


IMPLEMENTATIONS: dict[str, dict[str, str]] = {
    "simulate": {"numpy": "spindle.simulation:simulate",
                 "c": "spindle.native.spindle:simulate"},
    "spindle_batch": {"c": "spindle.native.spindle:CSpindleBatch"},
    "tendon_organs": {"numpy": "spindle.tendon_organ:TendonOrgans",
                      "c": "spindle.native.tendon_organ:CTendonOrgans"},
    "chain": {"numpy": "spindle.chain.arm:ArmChain", "c": "spindle.native.chain:CArmChain"},
    "chain_batch": {"numpy": "spindle.chain.batch:ArmChainBatch",
                    "c": "spindle.native.chain:CArmChainBatch"},
    "stimulator": {"numpy": "spindle.stimulation.stimulator:NumpyStimulator",
                   "c": "spindle.native.stimulation:CStimulator"},
}
"""component -> backend -> ``module:attribute`` of its implementation (the spindle bank's
numpy path is its own code: it has only a C twin to load)."""


def implementation(component: str, backend: str = DEFAULT_BACKEND) -> tuple[str, Any]:
    """(the resolved backend, the class or function implementing ``component`` there),
    imported on first use (:data:`IMPLEMENTATIONS`).

    Raises:
        ValueError: ``backend`` is not one of :data:`BACKEND_CHOICES`, or ``component`` has
            no implementation on it.
    """
    name = resolve_backend(backend)
    path = IMPLEMENTATIONS.get(component, {}).get(name)
    if path is None:
        raise ValueError(f"{component!r} has no {name!r} implementation "
                         f"(it has {sorted(IMPLEMENTATIONS.get(component, {}))})")
    module, attribute = path.split(":")
    return name, getattr(importlib.import_module(module), attribute)


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
