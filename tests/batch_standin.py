"""A batched chain made of n single chains (``spindle.chain.make_chain``), the reference a
batched chain's arm k must equal, and a stand-in for ``spindle.chain.make_batched_chain`` /
``resolve_backend`` where the package does not provide them yet (``-p tests.batch_standin``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

import spindle.chain as chain_package
from spindle.chain import ArmSample, ChainConfig, make_chain


@dataclass(frozen=True)
class LoopBatchSample:
    t_s: np.ndarray
    accepted: np.ndarray
    counts: np.ndarray
    counts_filtered: np.ndarray
    angle_deg: np.ndarray
    length_L0: np.ndarray
    velocity_L0_s: np.ndarray
    acceleration_L0_s2: np.ndarray
    template_L0: np.ndarray
    gamma_static_pps: np.ndarray
    gamma_dynamic_pps: np.ndarray
    ia_pps: np.ndarray
    ii_pps: np.ndarray

    @classmethod
    def stack(cls, samples: list[ArmSample]) -> LoopBatchSample:
        return cls(**{f.name: np.array([getattr(s, f.name) for s in samples])
                      for f in fields(cls)})


class LoopBatchedChain:
    """n single chains behind the batched API (one Python call per arm)."""

    def __init__(self, n_arms: int, config: ChainConfig | None = None, fits=None) -> None:
        config = ChainConfig() if config is None else config
        self.n_arms, self.config = n_arms, config
        self.chains = [make_chain(config, fits) for _ in range(n_arms)]
        self._last: list[ArmSample | None] = [None] * n_arms

    @property
    def last(self) -> LoopBatchSample:
        return LoopBatchSample.stack(self._last)

    @property
    def counters(self) -> dict[str, np.ndarray]:
        names = self.chains[0].counters
        return {k: np.array([c.counters[k] for c in self.chains]) for k in names}

    def reset(self, angle_deg, t_s=0.0, length_L0=None, arms=None):
        arms = np.arange(self.n_arms) if arms is None else np.asarray(arms)
        t = np.broadcast_to(np.asarray(t_s, dtype=float), arms.shape)
        for j, i in enumerate(arms.tolist()):
            kw = {} if length_L0 is None else {"length_L0": np.asarray(length_L0)[j]}
            self._last[i] = self.chains[i].reset(float(angle_deg[j]), float(t[j]), **kw)
        return self.last

    def _block(self, name, t_s, x, n_samples):
        n_samples = (np.full(self.n_arms, t_s.shape[1]) if n_samples is None
                     else np.asarray(n_samples))
        for i, c in enumerate(self.chains):
            k = int(n_samples[i])
            if k == 0:
                self._last[i] = replace(self._last[i], accepted=False)
            else:
                self._last[i] = getattr(c, name)(t_s[i, :k], x[i, :k])
        return self.last

    def push_counts_block(self, t_s, counts, n_samples=None):
        return self._block("push_counts_block", t_s, counts, n_samples)

    def push_angle_block(self, t_s, angle_deg, n_samples=None):
        return self._block("push_angle_block", t_s, angle_deg, n_samples)

    def push_lengths_block(self, t_s, length_L0, n_samples=None):
        return self._block("push_lengths_block", t_s, length_L0, n_samples)


def _resolve_backend(backend: str = "auto") -> str:
    if backend != "auto":
        return backend
    try:
        from spindle.native.chain import CArmChain

        CArmChain(ChainConfig(backend="c"))
        return "c"
    except Exception:
        return "numpy"


if not hasattr(chain_package, "make_batched_chain"):
    chain_package.make_batched_chain = LoopBatchedChain
if not hasattr(chain_package, "resolve_backend"):
    chain_package.resolve_backend = _resolve_backend
