"""The stimulator object users hold: numpy or C behind one interface, streaming and batch.

:func:`make_stimulator` is the one place that knows both implementations (it loads the C
binding only for ``backend="c"``, or ``"auto"`` where the library builds).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from spindle.backends import DEFAULT_BACKEND, implementation
from spindle.stimulation import encoder
from spindle.stimulation.config import StimConfig
from spindle.stimulation.encoder import COUNTERS, EncoderState
from spindle.stimulation.events import empty_events
from spindle.stimulation.trace import checked_trace


class PulseStimulator(Protocol):
    """What both implementations offer."""

    config: StimConfig
    backend: str

    def reset(self, t0_s: float = 0.0) -> None: ...
    def step(self, rates_pps: object, dt_s: float) -> np.ndarray: ...
    def run(self, rates_pps: object, dt_s: object) -> np.ndarray: ...
    @property
    def channel_counters(self) -> np.ndarray: ...
    @property
    def counters(self) -> dict[str, int]: ...


class NumpyStimulator:
    """The numpy encoder (:mod:`spindle.stimulation.encoder`) with its state."""

    backend = "numpy"

    def __init__(self, config: StimConfig, t0_s: float = 0.0) -> None:
        self.config = config
        self.reset(t0_s)

    def reset(self, t0_s: float = 0.0) -> None:
        """Every channel at rest at ``t0_s``; counters zero."""
        self.state: EncoderState = encoder.initial_state(self.config, t0_s)

    def step(self, rates_pps: object, dt_s: float) -> np.ndarray:
        """The pulses of one interval ``[t, t + dt_s)`` for rates (channels,) held over it."""
        self.state, events = encoder.step(self.config, self.state, rates_pps, dt_s)
        return events

    def run(self, rates_pps: object, dt_s: object) -> np.ndarray:
        """A whole trace: row i of ``rates_pps`` (T, channels) held over ``dt_s[i]`` (or a
        scalar), exactly the steps in order; the state is unchanged if the input is bad."""
        rates, dt = checked_trace(self.config, rates_pps, dt_s)
        state, chunks = self.state, []
        for i in range(rates.shape[0]):
            state, events = encoder.step(self.config, state, rates[i], float(dt[i]))
            chunks.append(events)
        self.state = state
        return np.concatenate(chunks) if chunks else empty_events()

    @property
    def t_s(self) -> float:
        return self.state.t_s

    @property
    def channel_counters(self) -> np.ndarray:
        """(channels, len(COUNTERS)) int64 counts."""
        return self.state.counts.copy()

    @property
    def counters(self) -> dict[str, int]:
        """Each counter summed over channels."""
        return dict(zip(COUNTERS, (int(v) for v in self.state.counts.sum(axis=0)), strict=True))


def make_stimulator(config: StimConfig | None = None, backend: str = DEFAULT_BACKEND,
                    t0_s: float = 0.0) -> PulseStimulator:
    """The stimulator of ``config`` (default :class:`StimConfig`) on ``backend``
    (``"numpy" | "c" | "auto"``, resolved by :func:`spindle.backends.resolve_backend`), at
    rest at ``t0_s``."""
    config = StimConfig() if config is None else config
    if not isinstance(config, StimConfig):
        raise TypeError(f"config must be a StimConfig, got {type(config).__name__}")
    if not (isinstance(t0_s, int | float) and math.isfinite(t0_s)):
        raise ValueError(f"t0_s={t0_s!r} must be a finite number")
    return implementation("stimulator", backend)[1](config, t0_s)
