"""The stimulator's limits and the charge-safety check a configuration must pass.

Charge per phase ``Q`` (µC) and charge density ``D = Q / A`` (µC/cm², ``A`` the geometric
area) of a channel's largest pulse are checked against the Shannon (1992) criterion
(IEEE Trans Biomed Eng 39:424, fitted to McCreery et al.'s tissue-damage data)::

    log10(D) = k - log10(Q),   i.e.   k = log10(Q) + log10(Q / A) <= k_max

with ``k_max = 1.85`` (the smallest k at which damage was seen), and against an optional
charge-per-phase ceiling of the device. A channel map that fails either is refused with a
``ValueError`` naming the channel, its value and the limit, before anything runs. The
criterion was fitted on macroelectrodes; for microelectrodes it is a necessary, not a
sufficient, check (Cogan et al. 2016 J Neural Eng 13:021001).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from spindle.stimulation.channels import ChannelMap
from spindle.stimulation.checks import is_real

MAX_RATE_CEILING_PPS = 10_000.0
"""Largest per-channel pulse rate a configuration may declare (a pulse per 100 µs)."""


@dataclass(frozen=True)
class StimulatorLimits:
    """What the stimulator can and may deliver.

    Attributes:
        max_rate_pps: largest pulse rate of a channel: encoded rates are clipped to it
            (``rate_clipped``); the deterministic modes then never place two pulses of a
            channel closer than ``1 / max_rate_pps``.
        max_total_rate_pps: largest pulse rate summed over channels, or None for no limit:
            no two pulses of any channels start closer than ``1 / max_total_rate_pps``
            (one multiplexed current source). Priority rule: pulses are taken in time order
            (ties: lower channel index first) and one that comes too soon after the last
            delivered pulse is dropped (``dropped_total_rate``), never delayed.
        shannon_k: the Shannon criterion's ``k_max``.
        max_charge_nC: largest charge per phase (nC) the device may deliver.
        min_interval_us: extra time a channel waits after a pulse's last phase: the next
            pulse of a channel starts no earlier than ``duration_us + min_interval_us``
            after the previous one (``dropped_interval`` counts any that would).

    Defaults (assumed): 300 pps per channel (above the 0-200 pps of human Ia/II), no
    total-rate limit, k_max 1.85 (Shannon 1992), 100 nC per phase, no extra interval.
    """

    max_rate_pps: float = 300.0
    max_total_rate_pps: float | None = None
    shannon_k: float = 1.85
    max_charge_nC: float = 100.0
    min_interval_us: int = 0

    def __post_init__(self) -> None:
        _positive("max_rate_pps", self.max_rate_pps, MAX_RATE_CEILING_PPS)
        if self.max_total_rate_pps is not None:
            _positive("max_total_rate_pps", self.max_total_rate_pps, 1e6)
        _positive("max_charge_nC", self.max_charge_nC, 1e6)
        if not (is_real(self.shannon_k) and math.isfinite(self.shannon_k)):
            raise ValueError(f"shannon_k={self.shannon_k!r} must be a finite number")
        if (isinstance(self.min_interval_us, bool) or not isinstance(self.min_interval_us, int)
                or not 0 <= self.min_interval_us <= 1_000_000):
            raise ValueError(f"min_interval_us={self.min_interval_us!r} must be an int in "
                             "[0, 1000000]")

    @property
    def min_total_spacing_s(self) -> float:
        """Shortest time between any two pulses (0 without a total-rate limit)."""
        return 0.0 if self.max_total_rate_pps is None else 1.0 / self.max_total_rate_pps


def _positive(name: str, value: object, ceiling: float) -> None:
    if not (is_real(value) and math.isfinite(value) and 0 < value <= ceiling):
        raise ValueError(f"{name}={value!r} must be a finite number in (0, {ceiling:g}]")


def shannon_k(charge_uC: float, area_cm2: float) -> float:
    """k = log10(Q) + log10(Q / A) of a phase of ``charge_uC`` on ``area_cm2``."""
    return math.log10(charge_uC) + math.log10(charge_uC / area_cm2)


def min_interval_s(channels: ChannelMap, limits: StimulatorLimits) -> list[float]:
    """Per channel: the shortest time between two of its pulses' starts (s)."""
    return [(c.duration_us + limits.min_interval_us) * 1e-6 for c in channels.channels]


def check_safety(channels: ChannelMap, limits: StimulatorLimits) -> None:
    """Refuse (``ValueError``) a channel whose largest pulse breaks a charge limit, or whose
    pulse does not fit in the interval the maximum rate leaves."""
    for c in channels.channels:
        q_uC = c.max_charge_pC * 1e-6
        if q_uC * 1e3 > limits.max_charge_nC:
            raise ValueError(
                f"channel {c.label!r}: {c.max_uA} µA x {c.phase_us} µs = {q_uC * 1e3:g} nC "
                f"per phase exceeds the limit max_charge_nC={limits.max_charge_nC:g}")
        k = shannon_k(q_uC, c.area_cm2)
        if k > limits.shannon_k:
            raise ValueError(
                f"channel {c.label!r}: {q_uC * 1e3:g} nC per phase on {c.area_cm2:g} cm² "
                f"({q_uC / c.area_cm2:g} µC/cm²) gives Shannon k = {k:.3f}, above the limit "
                f"shannon_k={limits.shannon_k:g}")
        needed_us = c.duration_us + limits.min_interval_us
        if needed_us * 1e-6 * limits.max_rate_pps > 1.0:
            raise ValueError(
                f"channel {c.label!r}: a pulse takes {needed_us} µs (2 x {c.phase_us} µs + "
                f"{c.gap_us} µs gap + {limits.min_interval_us} µs), longer than the "
                f"1/max_rate_pps = {1e6 / limits.max_rate_pps:g} µs between pulses")
