"""The sensory side of an env step: physics samples in, one :class:`~spindle.chain.ArmSample` out.

Three sources feed the spindle chain (``spindle.chain.make_chain``: numpy or C) at different
stages:

- ``"exact"``: MuJoCo's fibre lengths (tendon path -> :mod:`proprio_env.muscle_length`), one
  sample per physics step (2 ms, 500 Hz);
- ``"reduced"``: MuJoCo's elbow angle through the fitted length model, one sample per physics
  step;
- ``"encoder"``: a simulated AX-12 encoder (:class:`proprio_env.encoder.Encoder`: jittered
  ~500 Hz sample times, 0.29 deg counts, noise, rare invalid readings) reading the elbow
  angle, then the prosthesis chain (median filter, f(x), fitted lengths), as in the seed paper.

Every source pushes all the samples of one env step in one block call
(``push_*_block``), which a compiled chain backend runs in one call.
"""

from __future__ import annotations

import numpy as np

from proprio_env.encoder import Encoder, EncoderBank
from spindle.chain import ArmSample, ChainConfig, make_batched_chain, make_chain
from spindle.chain.length_model import LengthFits
from spindle.chain.sensor import AX12, EncoderParams

SOURCES = ("exact", "reduced", "encoder")
"""Names of the afferent sources (see the module docstring)."""


def check_source(source: str) -> str:
    """``source`` if it is one of :data:`SOURCES`, else ValueError naming the choices."""
    if not (isinstance(source, str) and source in SOURCES):
        raise ValueError(f"afferent_source={source!r} is not one of {SOURCES}")
    return source


def encoder_window(step_s: float, params: EncoderParams) -> int:
    """The most encoder readings one env step of ``step_s`` can hold, plus two (a reading
    interval is at least 60 % of the nominal period)."""
    return int(step_s / (0.6 * params.period_s)) + 3


class AfferentReadout:
    """One arm's spindle chain fed by one source.

    Args:
        source: one of :data:`SOURCES`.
        chain_config: the chain's settings (:class:`~spindle.chain.ChainConfig`).
        encoder_params: the simulated encoder (only for ``"encoder"``).
        fits: the length fits of the arm's model (``None``: loaded from
            ``chain_config.fits_path``, by default the bundled ones).
        step_s: the env step (s): bounds the encoder readings per push.
    """

    def __init__(self, source: str, chain_config: ChainConfig,
                 encoder_params: EncoderParams = AX12,
                 fits: LengthFits | None = None, step_s: float = 0.02) -> None:
        self.source = check_source(source)
        self.chain = make_chain(chain_config, fits)
        self.encoder_params = encoder_params
        # the vector env's encoder code with one encoder: the same readings for a seed
        self.encoders = EncoderBank(1, encoder_params, encoder_window(step_s, encoder_params))

    @property
    def encoder(self) -> Encoder | None:
        """This episode's encoder (its random streams), ``None`` before the first reset."""
        return self.encoders.encoders[0]

    def reset(self, t_s: float, angle_deg: float, length_L0: np.ndarray,
              rng: np.random.Generator) -> ArmSample:
        """The arm at rest at ``angle_deg`` with fibre lengths ``length_L0`` at ``t_s``.

        ``rng`` drives the encoder's noise, jitter and glitches (the env's own generator, so a
        seeded reset reproduces them: the encoder spawns its streams from it).
        """
        if self.source == "exact":
            return self.chain.reset(angle_deg, t_s, length_L0=length_L0)
        sample = self.chain.reset(angle_deg, t_s)
        if self.source == "encoder":
            self.encoders.reset(0, float(t_s), float(angle_deg), rng)
        return sample

    def push(self, t_s: np.ndarray, angle_deg: np.ndarray,
             length_L0: np.ndarray | None) -> tuple[ArmSample, int]:
        """Push the physics samples of one env step; return the chain's output and how many
        sensor samples were pushed.

        Args:
            t_s: (n,) physics times after each physics step (increasing).
            angle_deg: (n,) elbow angle at those times.
            length_L0: (n, 2) exact fibre lengths at those times (``"exact"`` only).
        """
        if self.source == "exact":
            return self.chain.push_lengths_block(t_s, length_L0), t_s.size
        if self.source == "reduced":
            return self.chain.push_angle_block(t_s, angle_deg), t_s.size
        if self.encoder is None:
            raise RuntimeError("call AfferentReadout.reset before pushing samples")
        read_t, counts, n_samples = self.encoders.step(t_s[None, :], angle_deg[None, :])
        count = int(n_samples[0])
        if count == 0:
            return self.chain.last, 0
        return self.chain.push_counts_block(read_t[0, :count], counts[0, :count]), count


class BatchAfferentReadout:
    """The spindle chains of ``n`` arms fed by one source, all pushed in one batched call
    (:func:`spindle.chain.make_batched_chain`); arm i reads as an :class:`AfferentReadout`.

    Args:
        n: number of arms.
        source, chain_config, encoder_params, fits, step_s: as :class:`AfferentReadout`.
    """

    def __init__(self, n: int, source: str, chain_config: ChainConfig,
                 encoder_params: EncoderParams = AX12, fits: LengthFits | None = None,
                 step_s: float = 0.02) -> None:
        self.n = n
        self.source = check_source(source)
        self.chain = make_batched_chain(n, chain_config, fits)
        self.encoder_params = encoder_params
        self.encoders = EncoderBank(n, encoder_params, encoder_window(step_s, encoder_params))

    def reset(self, arms: np.ndarray, t_s: np.ndarray, angle_deg: np.ndarray,
              length_L0: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Arms ``arms`` (m,) at rest at ``angle_deg`` (m,) with fibre lengths ``length_L0``
        (m, 2) at ``t_s`` (m,); ``rngs`` are those arms' env generators (the encoders
        spawn their streams from them, in the order of ``arms``)."""
        if self.source == "exact":
            self.chain.reset(angle_deg, t_s, length_L0=length_L0, arms=arms)
            return
        self.chain.reset(angle_deg, t_s, arms=arms)
        if self.source == "encoder":
            for j, i in enumerate(arms.tolist()):
                self.encoders.reset(i, float(t_s[j]), float(angle_deg[j]), rngs[j])

    def push(self, t_s: np.ndarray, angle_deg: np.ndarray, length_L0: np.ndarray | None,
             active: np.ndarray) -> tuple[object, np.ndarray]:
        """Push one env step of every arm with ``active`` set (the others get no sample);
        return the chain's output (a ``BatchSample``) and the samples pushed per arm (n,).

        Args:
            t_s: (n, F) physics times after each physics step.
            angle_deg: (n, F) elbow angles at those times.
            length_L0: (n, F, 2) exact fibre lengths (``"exact"`` only).
            active: (n,) bool.
        """
        frames = t_s.shape[1]
        if self.source == "encoder":
            read_t, counts, n_samples = self.encoders.step(t_s, angle_deg)
            n_samples = np.where(active, n_samples, 0)
            return self.chain.push_counts_block(read_t, counts, n_samples), n_samples
        n_samples = np.where(active, frames, 0)
        if self.source == "exact":
            return self.chain.push_lengths_block(t_s, length_L0, n_samples), n_samples
        return self.chain.push_angle_block(t_s, angle_deg, n_samples), n_samples
