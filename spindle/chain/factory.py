"""The one place that knows both chains: :func:`make_chain` and :func:`make_batched_chain`
build the numpy or the C one, :func:`resolve_backend` says which ``"auto"`` means here."""

from __future__ import annotations

import os
from dataclasses import replace
from functools import cache

from spindle.chain.arm import ArmChain
from spindle.chain.config import BACKEND_CHOICES, Chain, ChainConfig
from spindle.chain.length_model import LengthFits


def resolve_backend(name: str) -> str:
    """The backend ``name`` selects: ``"numpy"`` or ``"c"``.

    ``"auto"`` is ``"c"`` when the native library can be used here: a valid cached build (see
    :mod:`spindle.native.build`), or a C compiler that builds it now (once: the build is
    cached and the chain loads that same library); otherwise ``"numpy"``. It never raises
    for a missing or failing compiler, a damaged cache or a library that does not load: each
    falls back to numpy.

    Raises:
        ValueError: ``name`` is not one of :data:`~spindle.chain.config.BACKEND_CHOICES`.
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
    failing build is tried once per setting, not at every chain built."""
    del cc, cache_dir  # the cache key: what the build reads from the environment
    try:
        # imported here so that numpy-only use of the chain never loads ctypes or the C build
        from spindle.native.chain import library

        library("double")
    except Exception:  # any reason the library cannot be used means numpy
        return False
    return True


def _resolved(config: ChainConfig | None) -> ChainConfig:
    config = ChainConfig() if config is None else config
    backend = resolve_backend(config.backend)
    return config if backend == config.backend else replace(config, backend=backend)


def make_chain(config: ChainConfig | None = None, fits: LengthFits | None = None) -> Chain:
    """The chain ``config.backend`` names: :class:`~spindle.chain.arm.ArmChain` (numpy) or
    :class:`~spindle.native.chain.CArmChain` (C, compiled on first use; raises
    :class:`~spindle.native.build.CBackendError` without a C compiler); ``"auto"``: as
    :func:`resolve_backend` decides. The chain's ``config.backend`` is the resolved one."""
    config = _resolved(config)
    if config.backend == "c":
        from spindle.native.chain import CArmChain

        return CArmChain(config, fits)
    return ArmChain(config, fits)


def make_batched_chain(n_arms: int, config: ChainConfig | None = None,
                       fits: LengthFits | None = None):
    """``n_arms`` chains advanced together, of the backend ``config.backend`` names:
    :class:`~spindle.chain.batch.BatchedArmChain` (numpy) or
    :class:`~spindle.native.chain.CBatchedArmChain` (C, one C call per push for all arms);
    ``"auto"`` as :func:`resolve_backend` decides. Both have the same API; the chain's
    ``config.backend`` is the resolved one."""
    config = _resolved(config)
    if config.backend == "c":
        from spindle.native.chain import CBatchedArmChain

        return CBatchedArmChain(n_arms, config, fits)
    from spindle.chain.batch import BatchedArmChain

    return BatchedArmChain(n_arms, config, fits)
