"""What runs on the prosthesis: the seed paper's processing chain for one arm.

    counts -> median filter, f(x) (sensor) -> elbow angle -> fitted fibre lengths
    (length_model) -> tracking low-pass (conditioning) -> PI template, gamma_s, gamma_d
    (fusimotor) -> Mileusnic spindles (spindle.core) -> Ia, II per muscle
    load word (sensor) -> torque -> BRA/TRImed tendon forces (force) -> Golgi tendon
    organs (spindle.tendon_organ) -> Ib per muscle

:class:`ArmChain` (numpy, :mod:`spindle.chain.arm`) streams sample by sample; its C mirror is
:class:`spindle.native.chain.CArmChain`. :func:`make_chain` builds the one
``ChainConfig.backend`` names (``"auto"``: :func:`resolve_backend`), :func:`make_batched_chain`
the batch of many arms advanced by one call (numpy ``spindle.chain.batch.ArmChainBatch`` or
C :class:`spindle.native.chain.CArmChainBatch`); :func:`run_chain` runs a whole trace
through a chain. No MuJoCo here.
"""

from spindle.chain.arm import ArmChain
from spindle.chain.config import (
    BACKEND_CHOICES,
    BACKENDS,
    COUNTERS,
    MUSCLES,
    ArmSample,
    Chain,
    ChainConfig,
)
from spindle.chain.factory import make_batched_chain, make_chain, resolve_backend
from spindle.chain.trace import ChainTrace, run_chain

__all__ = [
    "BACKENDS",
    "BACKEND_CHOICES",
    "COUNTERS",
    "MUSCLES",
    "ArmChain",
    "ArmSample",
    "Chain",
    "ChainConfig",
    "ChainTrace",
    "make_batched_chain",
    "make_chain",
    "resolve_backend",
    "run_chain",
]
