"""The one place that knows both chains: :func:`make_chain` builds the numpy or the C one."""

from __future__ import annotations

from spindle.chain.arm import ArmChain
from spindle.chain.config import Chain, ChainConfig
from spindle.chain.length_model import LengthFits


def make_chain(config: ChainConfig | None = None, fits: LengthFits | None = None) -> Chain:
    """The chain ``config.backend`` names: :class:`~spindle.chain.arm.ArmChain` (numpy) or
    :class:`~spindle.native.chain.CArmChain` (C, compiled on first use; raises
    :class:`~spindle.native.build.CBackendError` without a C compiler)."""
    config = ChainConfig() if config is None else config
    if config.backend == "c":
        # imported here so that numpy-only use of the chain never loads ctypes or the C build
        from spindle.native.chain import CArmChain

        return CArmChain(config, fits)
    return ArmChain(config, fits)
