"""Which afferent drives which electrode channel, and each channel's pulse shape.

A channel is one stimulating electrode site with its own current range and pulse shape. The
channel map is a tuple of channels; its order is the channel index of every per-channel
array, of the pulse events (``channel``) and of the total-rate priority (lower index first).
Any (muscle, afferent) pair with afferent in :data:`AFFERENTS` (``"ia"``, ``"ii"``, ``"ib"``)
can drive a channel, so tendon-organ (Ib) rates plug in beside the spindles' Ia and II.

Units: currents in integer µA, times in integer µs (what a stimulator is programmed in), the
electrode's geometric area in cm² (the unit of the Shannon criterion). Charge per phase is
then the exact integer ``amplitude_uA * phase_us`` in pC (1 µA·µs = 1 pC).

Defaults (assumed, to be replaced by each electrode's fitted values: every study measures
thresholds per site): an intrafascicular site 80 µm across (the active sites of the TIME
electrode, Boretius et al. 2010 Biosens Bioelectron 26:62: 5.03e-5 cm²), symmetric
cathodic-first biphasic pulses of 100 µs per phase with a 50 µs interphase gap, perception
threshold 30 µA and maximum 150 µA (15 nC/phase; Shannon k = 0.65 on that area, below
1.85).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

AFFERENTS = ("ia", "ii", "ib")
"""Afferent kinds a channel may carry: spindle primary (Ia), secondary (II), tendon organ
(Ib)."""

TIME_SITE_AREA_CM2 = math.pi * (40e-4) ** 2
"""Geometric area of an 80 µm-diameter site (5.03e-5 cm²)."""

MAX_AMPLITUDE_UA = 10_000
"""Largest amplitude a channel may declare (10 mA: beyond any implanted nerve stimulator)."""
MAX_PHASE_US = 10_000
"""Largest phase width or interphase gap a channel may declare (10 ms)."""


@dataclass(frozen=True)
class Channel:
    """One electrode channel: what drives it and the pulses it can deliver.

    Attributes:
        muscle: the muscle whose afferent drives it (e.g. ``"BRA"``, ``"TRImed"``).
        afferent: one of :data:`AFFERENTS`.
        threshold_uA: perception threshold: the smallest amplitude delivered.
        max_uA: the largest amplitude delivered (comfort limit); the fixed-amplitude modes
            deliver this one.
        phase_us: width of each phase (cathodic, then anodic of the same width and
            amplitude: the pulse's charges are equal as integers).
        gap_us: interphase gap.
        area_cm2: geometric electrode area (Shannon criterion).
    """

    muscle: str
    afferent: str
    threshold_uA: int = 30
    max_uA: int = 150
    phase_us: int = 100
    gap_us: int = 50
    area_cm2: float = TIME_SITE_AREA_CM2

    def __post_init__(self) -> None:
        if not isinstance(self.muscle, str) or not self.muscle:
            raise ValueError(f"muscle={self.muscle!r} must be a non-empty string")
        if self.afferent not in AFFERENTS:
            raise ValueError(f"afferent={self.afferent!r} is not one of {AFFERENTS}")
        for name, lo, hi in (("threshold_uA", 1, MAX_AMPLITUDE_UA),
                             ("max_uA", 1, MAX_AMPLITUDE_UA),
                             ("phase_us", 1, MAX_PHASE_US), ("gap_us", 0, MAX_PHASE_US)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise TypeError(f"{self.label}: {name}={value!r} must be an int")
            if not lo <= value <= hi:
                raise ValueError(f"{self.label}: {name}={value!r} outside [{lo}, {hi}]")
        if self.threshold_uA > self.max_uA:
            raise ValueError(f"{self.label}: threshold_uA={self.threshold_uA} exceeds "
                             f"max_uA={self.max_uA}")
        if not (isinstance(self.area_cm2, int | float) and math.isfinite(self.area_cm2)
                and self.area_cm2 > 0):
            raise ValueError(f"{self.label}: area_cm2={self.area_cm2!r} must be finite and > 0")

    @property
    def label(self) -> str:
        return f"{self.muscle} {self.afferent}"

    @property
    def duration_us(self) -> int:
        """Both phases and the gap: the time one pulse occupies its channel."""
        return 2 * self.phase_us + self.gap_us

    @property
    def max_charge_pC(self) -> int:
        """Charge of one phase at ``max_uA`` (pC = µA·µs)."""
        return self.max_uA * self.phase_us


@dataclass(frozen=True)
class ChannelMap:
    """The channels in index order; a (muscle, afferent) pair drives at most one channel."""

    channels: tuple[Channel, ...]

    def __post_init__(self) -> None:
        channels = tuple(self.channels)
        object.__setattr__(self, "channels", channels)
        if not channels:
            raise ValueError("a channel map needs at least one channel")
        if not all(isinstance(c, Channel) for c in channels):
            raise TypeError("every entry of channels must be a Channel")
        keys = [(c.muscle, c.afferent) for c in channels]
        for key in keys:
            if keys.count(key) > 1:
                raise ValueError(f"(muscle, afferent)={key} drives more than one channel")

    def __len__(self) -> int:
        return len(self.channels)

    def index(self, muscle: str, afferent: str) -> int:
        """The channel (muscle, afferent) drives; KeyError naming the map's pairs if none."""
        for k, c in enumerate(self.channels):
            if c.muscle == muscle and c.afferent == afferent:
                return k
        raise KeyError(f"no channel for ({muscle!r}, {afferent!r}); the map has "
                       f"{[(c.muscle, c.afferent) for c in self.channels]}")

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(c.label for c in self.channels)

    def gather(self, rates_pps: Mapping[tuple[str, str], object]) -> np.ndarray:
        """The channels' rates from rates keyed by (muscle, afferent), stacked on a last axis
        in channel order: scalars give (channels,), (T,) arrays give (T, channels). Pairs no
        channel uses are ignored; a channel whose pair is missing is a KeyError naming it."""
        missing = [c.label for c in self.channels if (c.muscle, c.afferent) not in rates_pps]
        if missing:
            raise KeyError(f"no rate given for channel(s) {missing}")
        return np.stack([np.asarray(rates_pps[(c.muscle, c.afferent)], dtype=np.float64)
                         for c in self.channels], axis=-1)

    def array(self, name: str) -> list:
        """One attribute of every channel, in index order."""
        return [getattr(c, name) for c in self.channels]


def afferent_rates(muscles: tuple[str, ...] | list[str], **per_afferent: object
                   ) -> dict[tuple[str, str], np.ndarray]:
    """Rates keyed by (muscle, afferent) from per-afferent arrays whose last axis is
    ``muscles`` (e.g. a chain trace's ``ia_pps`` (T, 2) with ``muscles=("BRA", "TRImed")``):
    ``afferent_rates(MUSCLES, ia=trace.ia_pps, ii=trace.ii_pps)``; keywords are
    :data:`AFFERENTS`."""
    out: dict[tuple[str, str], np.ndarray] = {}
    for afferent, values in per_afferent.items():
        if afferent not in AFFERENTS:
            raise ValueError(f"afferent={afferent!r} is not one of {AFFERENTS}")
        values = np.asarray(values, dtype=np.float64)
        if values.shape[-1:] != (len(muscles),):
            raise ValueError(f"{afferent} has shape {values.shape}; its last axis must be the "
                             f"{len(muscles)} muscles {tuple(muscles)}")
        for k, muscle in enumerate(muscles):
            out[(muscle, afferent)] = values[..., k]
    return out


def channel_map(pairs: list[tuple[str, str]] | tuple[tuple[str, str], ...],
                **shape: object) -> ChannelMap:
    """A map of one channel per (muscle, afferent) pair, all with the pulse shape ``shape``
    (keyword arguments of :class:`Channel`)."""
    return ChannelMap(tuple(Channel(m, a, **shape) for m, a in pairs))


ELBOW_SPINDLES = channel_map((("BRA", "ia"), ("BRA", "ii"), ("TRImed", "ia"),
                              ("TRImed", "ii")))
"""The demo's arm: Ia and II of the brachialis and the triceps medial head, default shape."""

ELBOW_ALL = channel_map((("BRA", "ia"), ("BRA", "ii"), ("BRA", "ib"), ("TRImed", "ia"),
                         ("TRImed", "ii"), ("TRImed", "ib")))
"""The same with the tendon organs (Ib) of both muscles."""
