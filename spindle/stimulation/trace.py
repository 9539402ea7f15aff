"""A trace's input: the rates of every sample interval and the intervals, checked once."""

from __future__ import annotations

import numpy as np

from spindle.stimulation.config import MAX_DT_S, StimConfig


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
        raise ValueError(f"dt_s[{i}]={float(dt[i])!r} must be a finite number in "
                         f"(0, {MAX_DT_S:g}] s")
    return rates, dt


def intervals_from_times(t_s: object) -> np.ndarray:
    """Sample times (T,) as the intervals each sample's rate is held over: ``t[i+1] - t[i]``,
    the last one repeating the one before (T >= 2)."""
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)):
        raise ValueError("t_s must be a 1-D array of >= 2 finite times")
    dt = np.diff(t)
    return np.append(dt, dt[-1])
