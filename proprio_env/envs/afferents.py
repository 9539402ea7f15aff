"""The sensory side of an env step: ``n`` arms' physics samples in, their chain outputs out.

Three sources feed the spindle chains (``spindle.chain.make_batched_chain``: numpy or C, all
arms in one call) at different stages:

- ``"exact"``: MuJoCo's fibre lengths (tendon path -> :mod:`proprio_env.body.muscle_length`), one
  sample per physics step (2 ms, 500 Hz);
- ``"reduced"``: MuJoCo's elbow angle through the fitted length model, one sample per physics
  step;
- ``"encoder"``: a simulated AX-12 encoder per arm (:class:`proprio_env.body.encoder.EncoderBatch`:
  jittered ~500 Hz sample times, 0.29 deg counts, noise, rare invalid readings) reading the
  elbow angle, then the prosthesis chain (median filter, f(x), fitted lengths), as in the
  seed paper.

Every source pushes all the samples of one env step of every arm in one block call
(``push_*_block``). A single env is one arm (n = 1), a vector env n arms: the same readout.
"""

from __future__ import annotations

import numpy as np

from proprio_env.body.encoder import EncoderBatch
from spindle.chain import ChainConfig, make_batched_chain
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
    """The spindle chains of ``n`` arms fed by one source, all pushed in one batched call.

    Args:
        source: one of :data:`SOURCES`.
        chain_config: the chains' settings (:class:`~spindle.chain.ChainConfig`).
        encoder_params: the simulated encoders (only for ``"encoder"``).
        fits: the length fits of the arms' model (``None``: loaded from
            ``chain_config.fits_path``, by default the bundled ones).
        step_s: the env step (s): bounds the encoder readings per push.
        n: number of arms (one per env).

    ``chain`` is the batched chain (its ``counters`` and outputs have a leading axis of
    arms), ``encoders`` the :class:`~proprio_env.body.encoder.EncoderBatch`.
    """

    def __init__(self, source: str, chain_config: ChainConfig,
                 encoder_params: EncoderParams = AX12, fits: LengthFits | None = None,
                 step_s: float = 0.02, n: int = 1) -> None:
        self.source = check_source(source)
        self.n = n
        self.chain = make_batched_chain(n, chain_config, fits)
        self.encoder_params = encoder_params
        self.encoders = EncoderBatch(n, encoder_params, encoder_window(step_s, encoder_params))
        self._all_frames: dict[int, np.ndarray] = {}

    def reset(self, arms: np.ndarray, t_s: np.ndarray, angle_deg: np.ndarray,
              length_L0: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Arms ``arms`` (m,) at rest at ``angle_deg`` (m,) with fibre lengths ``length_L0``
        (m, 2) at ``t_s`` (m,). ``rngs`` are those arms' env generators: each encoder spawns
        its noise, jitter and glitch streams from its own, so a seeded reset reproduces them.
        The first reset covers every arm."""
        arms = None if arms.size == self.n else arms
        if self.source == "exact":
            self.chain.reset(angle_deg, t_s, length_L0=length_L0, arms=arms)
            return
        self.chain.reset(angle_deg, t_s, arms=arms)
        if self.source == "encoder":
            rows = range(self.n) if arms is None else arms.tolist()
            for j, i in enumerate(rows):
                self.encoders.reset(i, float(t_s[j]), float(angle_deg[j]), rngs[j])

    def push(self, t_s: np.ndarray, angle_deg: np.ndarray, length_L0: np.ndarray | None,
             active: np.ndarray | None = None) -> tuple[object, np.ndarray]:
        """Push one env step of every arm with ``active`` set (None: all; the others get no
        sample); return the chain's output (a batch sample: arrays with a leading axis of
        arms) and the samples pushed per arm (n,).

        Args:
            t_s: (n, F) physics times after each physics step (increasing).
            angle_deg: (n, F) elbow angles at those times.
            length_L0: (n, F, 2) exact fibre lengths (``"exact"`` only).
            active: (n,) bool or None.
        """
        if self.source == "encoder":
            read_t, counts, n_samples = self.encoders.step(t_s, angle_deg)
            if active is not None:
                n_samples = np.where(active, n_samples, 0)
            return self.chain.push_counts_block(read_t, counts, n_samples), n_samples
        frames = t_s.shape[1]
        if active is None:
            # every arm pushes every frame: one read-only count array per block size
            n_samples, given = self._all_frames.get(frames), None
            if n_samples is None:
                n_samples = self._all_frames[frames] = np.full(self.n, frames)
                n_samples.flags.writeable = False
        else:
            n_samples = given = np.where(active, frames, 0)
        if self.source == "exact":
            return self.chain.push_lengths_block(t_s, length_L0, given), n_samples
        return self.chain.push_angle_block(t_s, angle_deg, given), n_samples
