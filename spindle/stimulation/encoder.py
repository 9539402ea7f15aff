"""The encoders in numpy: afferent rates into pulse events, one call per sample interval for
all channels (a leading axis of channels), and a whole trace by the same calls.

One call (:func:`step`) takes the rates (pps) held over ``[t, t + dt_s)``, and

1. applies the rate rules (per channel, counted): a non-finite rate is 0 for the interval and
   restarts the biomimetic derivative (``rate_nonfinite``), a negative one is 0
   (``rate_negative``), one above ``max_rate_pps`` is ``max_rate_pps`` (``rate_clipped``);
   nothing else can make pulses come faster, so no input makes a burst;
2. maps each rate to a pulse rate and an amplitude (:mod:`spindle.stimulation.modes`;
   ``amplitude_clipped`` counts drives above the channel's maximum);
3. integrates the pulse rate over the interval from each channel's phase, a pulse at every
   crossing of its threshold (1, or a gamma draw for ``"stochastic"``), its time
   interpolated within the interval (the rate is constant over it, so the crossing is
   exact); the stochastic mode waits the dead time after each pulse;
4. admits the candidates in time order (ties: lower channel first): one closer than the
   channel's minimum interval to its previous pulse is dropped (``dropped_interval``), then
   one closer than ``1 / max_total_rate_pps`` to the last pulse of any channel
   (``dropped_total_rate``).

A call that raises leaves the state as it was. The C encoder (``stimulation.c``) does the
same operations in the same order, channel by channel.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from spindle.stimulation.config import MAX_DT_S, StimConfig
from spindle.stimulation.events import PULSE_DTYPE
from spindle.stimulation.generator import gamma_threshold
from spindle.stimulation.modes import MODES
from spindle.stimulation.safety import min_interval_s

COUNTERS = ("pulses", "rate_nonfinite", "rate_negative", "rate_clipped", "amplitude_clipped",
            "dropped_interval", "dropped_total_rate")
"""Per-channel counters, in the order of ``ps_stim_state.counts`` (see the module doc)."""
_PULSES, _NONFINITE, _NEGATIVE, _CLIPPED, _AMP, _INTERVAL, _TOTAL = range(len(COUNTERS))


@dataclasses.dataclass
class EncoderState:
    """Everything an encoder changes; per-channel arrays have the channels on axis 0.

    Attributes:
        t_s: start of the next interval.
        phase: the pulse rate's integral since the last pulse (pulses).
        threshold: the integral at which the next pulse fires (1 when deterministic).
        resume_s: when integration resumes after the last pulse (its time plus dead time).
        last_pulse_s: start of the channel's last delivered pulse (-inf: none yet).
        previous_pps: the last rate, for the biomimetic derivative (NaN: none).
        draws: the number of thresholds drawn (the generator's counter, per channel).
        last_any_s: start of the last delivered pulse of any channel.
        counts: (channels, len(COUNTERS)) int64 counters.
    """

    t_s: float
    phase: np.ndarray
    threshold: np.ndarray
    resume_s: np.ndarray
    last_pulse_s: np.ndarray
    previous_pps: np.ndarray
    draws: np.ndarray
    last_any_s: float
    counts: np.ndarray

    def copy(self) -> EncoderState:
        return dataclasses.replace(self, **{f.name: np.copy(getattr(self, f.name))
                                            for f in dataclasses.fields(self)
                                            if isinstance(getattr(self, f.name), np.ndarray)})


def initial_state(config: StimConfig, t0_s: float = 0.0) -> EncoderState:
    """A channel at rest at ``t0_s``: phase 0, the first threshold drawn, no pulse yet."""
    if not (isinstance(t0_s, int | float) and math.isfinite(t0_s)):
        raise ValueError(f"t0_s={t0_s!r} must be a finite number")
    n = config.n_channels
    channel = np.arange(n)
    p = config.params
    if MODES[p.mode].stochastic:
        threshold = gamma_threshold(p.seed, channel, np.zeros(n, np.uint64), p.gamma_shape)
        draws = np.ones(n, np.uint64)
    else:
        threshold, draws = np.ones(n), np.zeros(n, np.uint64)
    return EncoderState(float(t0_s), np.zeros(n), threshold, np.full(n, float(t0_s)),
                        np.full(n, -np.inf), np.full(n, np.nan), draws, -np.inf,
                        np.zeros((n, len(COUNTERS)), np.int64))


def checked_step_input(config: StimConfig, rates_pps: object, dt_s: object) -> np.ndarray:
    """The rates as a float64 (channels,) array; ``ValueError`` for a bad shape or step."""
    if isinstance(dt_s, bool) or not isinstance(dt_s, int | float | np.floating) or \
            not (math.isfinite(dt_s) and 0 < dt_s <= MAX_DT_S):
        raise ValueError(f"dt_s={dt_s!r} must be a finite number in (0, {MAX_DT_S:g}] s")
    if np.iscomplexobj(rates_pps):
        raise ValueError("rates_pps must be real")
    rates = np.array(rates_pps, dtype=np.float64)
    if rates.shape != (config.n_channels,):
        raise ValueError(f"rates_pps has shape {rates.shape}, expected ({config.n_channels},)"
                         " (one rate per channel)")
    return rates


def step(config: StimConfig, state: EncoderState, rates_pps: object,
         dt_s: float) -> tuple[EncoderState, np.ndarray]:
    """One interval: (the new state, its pulse events in time order). ``state`` is unchanged."""
    rates = checked_step_input(config, rates_pps, dt_s)
    new = state.copy()
    t0 = new.t_s
    t1 = t0 + float(dt_s)
    rates = _rate_rules(config, new, rates)
    pulse_pps, amplitude = _drive(config, new, rates, float(dt_s))
    times, channels = _crossings(config, new, pulse_pps, t0, t1)
    events = _admit(config, new, times, channels, amplitude)
    new.t_s = t1
    return new, events


def _rate_rules(config: StimConfig, state: EncoderState, rates: np.ndarray) -> np.ndarray:
    nonfinite = ~np.isfinite(rates)
    rates[nonfinite] = 0.0
    negative = rates < 0
    rates[negative] = 0.0
    cap = config.limits.max_rate_pps
    clipped = rates > cap
    rates[clipped] = cap
    state.counts[:, _NONFINITE] += nonfinite
    state.counts[:, _NEGATIVE] += negative
    state.counts[:, _CLIPPED] += clipped
    state.previous_pps[nonfinite] = np.nan
    return np.where(nonfinite, np.nan, rates)  # NaN marks "stopped" for the drive


def _drive(config: StimConfig, state: EncoderState, rates: np.ndarray,
           dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(pulse rate (pps), amplitude (int µA)) per channel for this interval."""
    p, lim = config.params, config.limits
    stopped = np.isnan(rates)
    r = np.where(stopped, 0.0, rates)
    thr = np.array(config.channels.array("threshold_uA"), dtype=np.float64)
    top = np.array(config.channels.array("max_uA"), dtype=np.float64)
    if p.mode in ("frequency", "stochastic"):
        return r, top.astype(np.int32)
    level = np.minimum(r / p.full_scale_pps, 1.0)
    if p.mode == "amplitude":
        pulse = np.where(r > 0, p.carrier_pps, 0.0)
        amp_drive = r / p.full_scale_pps
    else:
        prev = state.previous_pps
        change = np.where(np.isnan(prev), 0.0, np.abs(r - prev) / dt_s)
        change = np.minimum(change / p.full_scale_change_pps_s, 1.0)
        pulse = lim.max_rate_pps * np.minimum(p.rate_level * level + p.rate_change * change,
                                              1.0)
        amp_drive = p.amp_level * level + p.amp_change * change
    state.previous_pps = np.where(stopped, np.nan, r)
    pulse = np.where(stopped, 0.0, pulse)
    state.counts[:, _AMP] += (amp_drive > 1.0) & (pulse > 0)
    amplitude = np.floor(thr + (top - thr) * np.minimum(amp_drive, 1.0) + 0.5)
    return pulse, amplitude.astype(np.int32)


def _crossings(config: StimConfig, state: EncoderState, pulse_pps: np.ndarray, t0: float,
               t1: float) -> tuple[np.ndarray, np.ndarray]:
    """Every threshold crossing in [t0, t1) (times, channels); updates phases and draws."""
    p = config.params
    stochastic = MODES[p.mode].stochastic
    dead = p.dead_time_s if stochastic else 0.0
    rate = pulse_pps / (1.0 - pulse_pps * dead) if stochastic else pulse_pps
    tau = np.maximum(t0, state.resume_s)
    active = (rate > 0) & (tau < t1)
    safe_rate = np.where(rate > 0, rate, 1.0)
    times, channels = [], []
    while active.any():
        with np.errstate(over="ignore"):  # a tiny rate's crossing is at +inf: never
            cross = np.maximum(tau + (state.threshold - state.phase) / safe_rate, tau)
        fire = active & (cross < t1)
        idle = active & ~fire
        state.phase[idle] += rate[idle] * (t1 - tau[idle])
        idx = np.flatnonzero(fire)
        times.append(cross[idx])
        channels.append(idx)
        state.phase[idx] = 0.0
        if stochastic:
            state.threshold[idx] = gamma_threshold(p.seed, idx, state.draws[idx],
                                                   p.gamma_shape)
            state.draws[idx] += np.uint64(1)
        tau[idx] = cross[idx] + dead
        state.resume_s[idx] = tau[idx]
        active = fire & (tau < t1)
    if not times:
        return np.zeros(0), np.zeros(0, np.int64)
    return np.concatenate(times), np.concatenate(channels)


def _admit(config: StimConfig, state: EncoderState, times: np.ndarray, channels: np.ndarray,
           amplitude: np.ndarray) -> np.ndarray:
    order = np.lexsort((channels, times))
    min_interval = min_interval_s(config.channels, config.limits)
    spacing = config.limits.min_total_spacing_s
    keep = np.zeros(order.size, bool)
    for j, k in enumerate(order):
        t, c = times[k], channels[k]
        if t - state.last_pulse_s[c] < min_interval[c]:
            state.counts[c, _INTERVAL] += 1
        elif t - state.last_any_s < spacing:
            state.counts[c, _TOTAL] += 1
        else:
            keep[j] = True
            state.last_pulse_s[c] = t
            state.last_any_s = t
            state.counts[c, _PULSES] += 1
    chosen = order[keep]
    out = np.zeros(chosen.size, dtype=PULSE_DTYPE)
    out["time_s"] = times[chosen]
    out["channel"] = channels[chosen]
    out["amplitude_uA"] = amplitude[channels[chosen]]
    phase = np.array(config.channels.array("phase_us"), dtype=np.int32)
    out["cathodic_us"] = phase[channels[chosen]]
    out["anodic_us"] = phase[channels[chosen]]
    out["gap_us"] = np.array(config.channels.array("gap_us"), dtype=np.int32)[channels[chosen]]
    return out
