"""The runtime's pluggable outputs: stages that make the rate stream's channels, and the
protocol of a pulse encoder that turns those rates into pulse events.

A **stage** has ``channel_labels`` and ``units`` (tuples of str, one per channel) and
``step(t_s, sample) -> values``: the (len(channel_labels),) float values for one accepted
sample (:class:`RuntimeSample`: the reading, with its load, and the chain's output). The
rate stream is the concatenation of the stages' channels, in order, after the runtime's
``reading_index`` channel. A stage is stepped once per published sample (the chain accepted
the reading, or rejected it and repeats its previous output), never for failed reads.

A **pulse encoder** has ``event_fields`` (the float fields of its events, in the order they
are streamed; ``t_s`` among them, the event's time on the runtime's clock) and
``step(t_s, rates) -> events``: a structured numpy array (any number of rows, zero
included) with at least those fields, given the rate stream's values of this sample; its
``bind(channel_labels, units)`` (optional) is called once before the first step with the rate
stream's layout.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from proprio_env.runtime.sources import Reading
from spindle.backends import DEFAULT_BACKEND
from spindle.chain import MUSCLES, ArmSample


@dataclass(frozen=True)
class RuntimeSample:
    """What a stage sees of one sample: the reading and the chain's output for it."""

    index: int
    t_s: float
    reading: Reading
    chain: ArmSample


@runtime_checkable
class Stage(Protocol):
    channel_labels: tuple[str, ...]
    units: tuple[str, ...]

    def step(self, t_s: float, sample: RuntimeSample) -> np.ndarray: ...


@runtime_checkable
class PulseEncoder(Protocol):
    event_fields: tuple[str, ...]

    def step(self, t_s: float, rates: np.ndarray) -> np.ndarray: ...


class SpindleStage:
    """The chain's afferents and their drives: Ia, II, gamma static, gamma dynamic and the
    tendon organs' Ib (from the servo's load word, which the chain reads with each reading)
    per muscle (pps), channels ``BRA_ia_pps, TRImed_ia_pps, BRA_ii_pps, ..., TRImed_ib_pps``."""

    FIELDS = ("ia_pps", "ii_pps", "gamma_static_pps", "gamma_dynamic_pps", "ib_pps")

    def __init__(self) -> None:
        self.channel_labels = tuple(f"{m}_{f}" for f in self.FIELDS for m in MUSCLES)
        self.units = ("pps",) * len(self.channel_labels)

    def step(self, t_s: float, sample: RuntimeSample) -> np.ndarray:
        c = sample.chain
        return np.concatenate([getattr(c, f) for f in self.FIELDS])


class LoadStage:
    """The servo's present load as a signed fraction of its full torque (channel
    ``servo_load``), as read (the chain's Ib comes from the same word: SpindleStage)."""

    channel_labels = ("servo_load",)
    units = ("fraction",)

    def step(self, t_s: float, sample: RuntimeSample) -> np.ndarray:
        return np.array([sample.reading.load_fraction])


def check_stage(stage: object) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The stage's labels and units, or a ``TypeError`` / ``ValueError`` naming what is off."""
    if not isinstance(stage, Stage):
        raise TypeError(f"{stage!r} is not a stage: it needs channel_labels, units and "
                        "step(t_s, sample)")
    labels, units = tuple(stage.channel_labels), tuple(stage.units)
    if len(labels) != len(units) or not labels:
        raise ValueError(f"{stage!r}: {len(labels)} channel labels and {len(units)} units "
                         "(need as many, at least one)")
    if not all(isinstance(x, str) and x for x in labels + units):
        raise ValueError(f"{stage!r}: channel labels and units must be non-empty strings")
    return labels, units


def check_pulse_encoder(encoder: object) -> tuple[str, ...]:
    """The encoder's event fields, or a ``TypeError`` / ``ValueError``."""
    if not isinstance(encoder, PulseEncoder):
        raise TypeError(f"{encoder!r} is not a pulse encoder: it needs event_fields and "
                        "step(t_s, rates)")
    fields = tuple(encoder.event_fields)
    if "t_s" not in fields or len(set(fields)) != len(fields):
        raise ValueError(f"{encoder!r}: event_fields {fields} must name distinct fields, "
                         "t_s among them")
    return fields


class StimulationEncoder:
    """The stimulator stage as the runtime's pulse encoder (:mod:`spindle.stimulation`):
    the rate stream's ``<muscle>_<afferent>_pps`` channel of every electrode channel of
    ``config`` (default: BRA and TRImed Ia, II and Ib, frequency coding), each sample's rates
    held until the next sample (causal), encoded into charge-balanced pulse events on the
    runtime's clock.

    An interval longer than the encoder's ``MAX_DT_S`` (1 s: the servo unplugged) or not
    after the last sample restarts the encoder at rest at the new sample: no pulses for the
    gap (``restarts``).
    """

    event_fields = ("t_s", "channel", "amplitude_uA", "cathodic_us", "gap_us", "anodic_us")

    def __init__(self, config: object | None = None, backend: str = DEFAULT_BACKEND) -> None:
        from spindle.stimulation import ELBOW_ALL, StimConfig, make_stimulator

        self.config = StimConfig(channels=ELBOW_ALL) if config is None else config
        self._stimulator = make_stimulator(self.config, backend)
        self.backend = self._stimulator.backend
        self._columns: np.ndarray | None = None
        self._last: tuple[float, np.ndarray] | None = None
        self.restarts = 0

    def bind(self, channel_labels: tuple[str, ...], units: tuple[str, ...]) -> None:
        wanted = [f"{c.muscle}_{c.afferent}_pps" for c in self.config.channels.channels]
        missing = [w for w in wanted if w not in channel_labels]
        if missing:
            raise ValueError(f"the rate stream has no channels {missing} for the stimulator "
                             f"(it has {list(channel_labels)})")
        self._columns = np.array([channel_labels.index(w) for w in wanted])

    def step(self, t_s: float, rates: np.ndarray) -> np.ndarray:
        from spindle.stimulation.config import MAX_DT_S

        if self._columns is None:
            raise RuntimeError("StimulationEncoder.step before bind")
        now = np.asarray(rates, dtype=float)[self._columns]
        last, self._last = self._last, (t_s, now)
        if last is None or not 0.0 < t_s - last[0] <= MAX_DT_S:
            self.restarts += last is not None
            self._stimulator.reset(t_s)
            return np.zeros(0, dtype=[(f, "<f8") for f in self.event_fields])
        pulses = self._stimulator.step(last[1], t_s - last[0])
        events = np.zeros(pulses.size, dtype=[(f, "<f8") for f in self.event_fields])
        events["t_s"] = pulses["time_s"]
        for name in self.event_fields[1:]:
            events[name] = pulses[name]
        return events
