"""The one place that knows both chains: :func:`make_chain` and :func:`make_batched_chain`
build the numpy or the C one (:func:`spindle.backends.resolve_backend` says which
``"auto"`` means here)."""

from __future__ import annotations

from dataclasses import replace

from spindle.backends import implementation, resolve_backend
from spindle.chain.config import Chain, ChainConfig
from spindle.chain.length_model import LengthFits


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
    return implementation("chain", config.backend)[1](config, fits)


def make_batched_chain(n_arms: int, config: ChainConfig | None = None,
                       fits: LengthFits | None = None):
    """``n_arms`` chains advanced together, of the backend ``config.backend`` names:
    :class:`~spindle.chain.batch.ArmChainBatch` (numpy) or
    :class:`~spindle.native.chain.CArmChainBatch` (C, one C call per push for all arms);
    ``"auto"`` as :func:`resolve_backend` decides. Both have the same API; the chain's
    ``config.backend`` is the resolved one."""
    config = _resolved(config)
    return implementation("chain_batch", config.backend)[1](n_arms, config, fits)
