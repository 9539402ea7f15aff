"""The stimulator object users hold: numpy or C behind one interface, streaming and batch.

:func:`make_stimulator` is the one place that knows both implementations (it loads the C
binding only for ``backend="c"``, or ``"auto"`` where the library builds).
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np

from spindle.backends import DEFAULT_BACKEND, resolve_backend
from spindle.stimulation import encoder
from spindle.stimulation.config import MAX_DT_S, StimConfig
from spindle.stimulation.encoder import COUNTERS, EncoderState
from spindle.stimulation.events import empty_events


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


def checked_trace(config: StimConfig, rates_pps: object,
                  dt_s: object) -> tuple[np.ndarray, np.ndarray]:
    """A trace's rates as float64 (T, channels) and its intervals as float64 (T,) (a scalar
    ``dt_s`` is every interval); ``ValueError`` for bad shapes or intervals."""
    if np.iscomplexobj(rates_pps) or np.iscomplexobj(dt_s):
        raise ValueError("rates_pps and dt_s must be real")
    rates = np.array(rates_pps, dtype=np.float64)
    if rates.ndim != 2 or rates.shape[1] != config.n_channels:
        raise ValueError(f"rates_pps has shape {rates.shape}, expected (T, "
                         f"{config.n_channels})")
    dt = np.broadcast_to(np.asarray(dt_s, dtype=np.float64), rates.shape[:1]).copy() \
        if np.ndim(dt_s) == 0 else np.array(dt_s, dtype=np.float64)
    if dt.shape != rates.shape[:1]:
        raise ValueError(f"dt_s has shape {dt.shape}, expected ({rates.shape[0]},)")
    bad = ~(np.isfinite(dt) & (dt > 0) & (dt <= MAX_DT_S))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"dt_s[{i}]={dt[i]!r} must be a finite number in (0, {MAX_DT_S:g}] s")
    return rates, dt


def intervals_from_times(t_s: object) -> np.ndarray:
    """Sample times (T,) as the intervals each sample's rate is held over: ``t[i+1] - t[i]``,
    the last one repeating the one before (T >= 2)."""
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)):
        raise ValueError("t_s must be a 1-D array of >= 2 finite times")
    dt = np.diff(t)
    return np.append(dt, dt[-1])


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
    if resolve_backend(backend) == "c":
        from spindle.native.stimulation import CStimulator  # C only when asked for

        return CStimulator(config, t0_s)
    return NumpyStimulator(config, t0_s)
