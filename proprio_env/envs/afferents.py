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

from proprio_env.encoder import Encoder
from spindle.chain import ArmSample, ChainConfig, make_chain
from spindle.chain.length_model import LengthFits
from spindle.chain.sensor import AX12, EncoderParams

SOURCES = ("exact", "reduced", "encoder")
"""Names of the afferent sources (see the module docstring)."""


def check_source(source: str) -> str:
    """``source`` if it is one of :data:`SOURCES`, else ValueError naming the choices."""
    if not (isinstance(source, str) and source in SOURCES):
        raise ValueError(f"afferent_source={source!r} is not one of {SOURCES}")
    return source


class AfferentReadout:
    """One arm's spindle chain fed by one source.

    Args:
        source: one of :data:`SOURCES`.
        chain_config: the chain's settings (:class:`~spindle.chain.ChainConfig`).
        encoder_params: the simulated encoder (only for ``"encoder"``).
        fits: the length fits of the arm's model (``None``: loaded from
            ``chain_config.fits_path``, by default the bundled ones).
    """

    def __init__(self, source: str, chain_config: ChainConfig,
                 encoder_params: EncoderParams = AX12,
                 fits: LengthFits | None = None) -> None:
        self.source = check_source(source)
        self.chain = make_chain(chain_config, fits)
        self.encoder_params = encoder_params
        self.encoder: Encoder | None = None
        self._next_read_s = 0.0
        self._t_s = 0.0
        self._angle_deg = 0.0

    def reset(self, t_s: float, angle_deg: float, length_L0: np.ndarray,
              rng: np.random.Generator) -> ArmSample:
        """The arm at rest at ``angle_deg`` with fibre lengths ``length_L0`` at ``t_s``.

        ``rng`` drives the encoder's noise, jitter and glitches (the env's own generator, so a
        seeded reset reproduces them).
        """
        self._t_s, self._angle_deg = float(t_s), float(angle_deg)
        if self.source == "exact":
            return self.chain.reset(angle_deg, t_s, length_L0=length_L0)
        sample = self.chain.reset(angle_deg, t_s)
        if self.source == "encoder":
            self.encoder = Encoder(self.encoder_params, rng=rng)
            self._next_read_s = self.encoder.next_sample_time_s(self._t_s)
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
            sample = self.chain.push_lengths_block(t_s, length_L0)
            count = t_s.size
        elif self.source == "reduced":
            sample = self.chain.push_angle_block(t_s, angle_deg)
            count = t_s.size
        else:
            sample, count = self._push_encoder(t_s, angle_deg)
        self._t_s, self._angle_deg = float(t_s[-1]), float(angle_deg[-1])
        return sample, count

    def _push_encoder(self, t_s: np.ndarray, angle_deg: np.ndarray) -> tuple[ArmSample, int]:
        encoder = self.encoder
        if encoder is None:
            raise RuntimeError("call AfferentReadout.reset before pushing samples")
        end = float(t_s[-1])
        times = []
        while self._next_read_s <= end:
            times.append(self._next_read_s)
            self._next_read_s = encoder.next_sample_time_s(self._next_read_s)
        if not times:
            return self.chain.last, 0
        # The encoder reads the angle between physics samples: linear interpolation over the
        # step, starting from the last angle of the previous step.
        knots_t = np.concatenate(([self._t_s], t_s))
        knots_a = np.concatenate(([self._angle_deg], angle_deg))
        read_t = np.asarray(times)
        counts = np.array([encoder.read(a) for a in np.interp(read_t, knots_t, knots_a)],
                          dtype=float)
        return self.chain.push_counts_block(read_t, counts), read_t.size
