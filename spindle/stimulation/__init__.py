"""The stimulator stage: afferent rates into safe, charge-balanced pulse trains per channel.

The seed paper's third stage ("an implanted neural stimulator to transmit these artificial
neural patterns"). Pieces, each usable alone:

- :mod:`~spindle.stimulation.channels`: :class:`Channel`, :class:`ChannelMap` (which
  (muscle, afferent) drives which electrode, its current range and pulse shape), presets;
- :mod:`~spindle.stimulation.safety`: :class:`StimulatorLimits`, the Shannon criterion;
- :mod:`~spindle.stimulation.modes`: :data:`MODES`, :class:`EncoderParams`;
- :mod:`~spindle.stimulation.config`: :class:`StimConfig` (all three, checked together);
- :mod:`~spindle.stimulation.generator`: the counter-based random draws (same bits in C);
- :mod:`~spindle.stimulation.encoder`: the numpy encoder (state, one step);
- :mod:`~spindle.stimulation.stimulator`: :func:`make_stimulator` (numpy or C);
- :mod:`~spindle.stimulation.trace`: a trace's checked input, :func:`intervals_from_times`;
- :mod:`~spindle.stimulation.events`: :data:`PULSE_DTYPE`, CSV and npz;
- :mod:`~spindle.stimulation.raster`: :func:`plot_raster` (matplotlib, imported lazily).
"""

from __future__ import annotations

from spindle.stimulation.channels import (
    AFFERENTS,
    ELBOW_ALL,
    ELBOW_SPINDLES,
    Channel,
    ChannelMap,
    afferent_rates,
    channel_map,
)
from spindle.stimulation.config import MAX_CHANNELS, StimConfig
from spindle.stimulation.encoder import COUNTERS
from spindle.stimulation.events import (
    PULSE_DTYPE,
    charges_pC,
    load_csv,
    load_npz,
    save_csv,
    save_npz,
)
from spindle.stimulation.modes import MODES, EncoderParams
from spindle.stimulation.raster import plot_raster
from spindle.stimulation.safety import StimulatorLimits, shannon_k
from spindle.stimulation.stimulator import NumpyStimulator, make_stimulator
from spindle.stimulation.trace import intervals_from_times

__all__ = [
    "AFFERENTS", "COUNTERS", "ELBOW_ALL", "ELBOW_SPINDLES", "MAX_CHANNELS", "MODES",
    "PULSE_DTYPE", "Channel", "ChannelMap", "EncoderParams", "NumpyStimulator", "StimConfig",
    "StimulatorLimits", "afferent_rates", "channel_map", "charges_pC", "intervals_from_times",
    "load_csv", "load_npz", "make_stimulator", "plot_raster", "save_csv", "save_npz",
    "shannon_k",
]
