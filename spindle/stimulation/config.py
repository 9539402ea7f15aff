"""One stimulator configuration: the channel map, the limits and the encoding, checked
together (a configuration that could break a limit is refused before anything runs)."""

from __future__ import annotations

from dataclasses import dataclass, field

from spindle.stimulation.channels import ELBOW_SPINDLES, ChannelMap
from spindle.stimulation.modes import MODES, EncoderParams
from spindle.stimulation.safety import StimulatorLimits, check_safety, min_interval_s

MAX_CHANNELS = 16
"""``PS_STIM_MAX_CHANNELS``: the most channels one configuration drives."""
MAX_DT_S = 1.0
"""Longest sample interval one call accepts (s)."""


@dataclass(frozen=True)
class StimConfig:
    """Channels, limits and encoding of one stimulator.

    Checked on construction (``ValueError`` naming the value and the limit): the charge
    safety of every channel (:func:`~spindle.stimulation.safety.check_safety`), at most
    :data:`MAX_CHANNELS` channels, the amplitude mode's carrier within ``max_rate_pps``, and
    for the stochastic mode a dead time no shorter than any channel's minimum interval with
    ``max_rate_pps * dead_time_s < 1`` (the rate the dead time leaves must stay finite).
    """

    channels: ChannelMap = ELBOW_SPINDLES
    limits: StimulatorLimits = field(default_factory=StimulatorLimits)
    params: EncoderParams = field(default_factory=EncoderParams)

    def __post_init__(self) -> None:
        if not isinstance(self.channels, ChannelMap):
            raise TypeError(f"channels must be a ChannelMap, got {type(self.channels).__name__}")
        if len(self.channels) > MAX_CHANNELS:
            raise ValueError(f"{len(self.channels)} channels exceed MAX_CHANNELS={MAX_CHANNELS}")
        check_safety(self.channels, self.limits)
        p, lim = self.params, self.limits
        if p.mode == "amplitude" and p.carrier_pps > lim.max_rate_pps:
            raise ValueError(f"carrier_pps={p.carrier_pps:g} exceeds max_rate_pps="
                             f"{lim.max_rate_pps:g}")
        if MODES[p.mode].stochastic:
            longest = max(min_interval_s(self.channels, lim))
            if p.dead_time_s < longest:
                raise ValueError(f"dead_time_s={p.dead_time_s:g} is shorter than a channel's "
                                 f"minimum interval {longest:g} s")
            if lim.max_rate_pps * p.dead_time_s >= 1.0:
                raise ValueError(f"max_rate_pps * dead_time_s = "
                                 f"{lim.max_rate_pps * p.dead_time_s:g} must be < 1")

    @property
    def n_channels(self) -> int:
        return len(self.channels)
