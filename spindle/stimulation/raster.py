"""A raster of pulse events over the rates that made them (matplotlib is the caller's)."""

from __future__ import annotations

import numpy as np


def plot_raster(ax, events: np.ndarray, labels: tuple[str, ...] | list[str],
                t_s: np.ndarray | None = None, rates_pps: np.ndarray | None = None,
                channels: list[int] | None = None, rate_scale_pps: float | None = None,
                amplitude_range_uA: tuple[float, float] | None = None) -> None:
    """Draw ``channels`` (default all) of ``events`` on ``ax``: one row per channel, a tick
    per pulse whose height grows with its amplitude, and, if given, each channel's rate
    (``t_s`` (T,), ``rates_pps`` (T, channels)) as a line scaled into its row (row height =
    ``rate_scale_pps``, default the largest rate drawn). Rows are labelled with ``labels``."""
    channels = list(range(len(labels))) if channels is None else list(channels)
    if rates_pps is not None and t_s is not None:
        shown = np.asarray(rates_pps)[:, channels]
        scale = rate_scale_pps or max(float(np.nanmax(shown)) if shown.size else 1.0, 1.0)
    amps = events["amplitude_uA"] if events.size else np.zeros(1)
    lo, hi = amplitude_range_uA or (float(amps.min()), float(amps.max()))
    for row, c in enumerate(channels):
        base = len(channels) - 1 - row
        mine = events[events["channel"] == c]
        height = 0.35 + 0.45 * ((mine["amplitude_uA"] - lo) / (hi - lo) if hi > lo else 1.0)
        ax.vlines(mine["time_s"], base, base + height, lw=0.6, color=f"C{row}")
        if rates_pps is not None and t_s is not None:
            ax.plot(t_s, base + 0.9 * np.asarray(rates_pps)[:, c] / scale, lw=0.8,
                    color="k", alpha=0.6)
    ax.set_yticks(np.arange(len(channels)) + 0.4)
    ax.set_yticklabels([labels[c] for c in reversed(channels)])
    ax.set_ylim(-0.1, len(channels))
    ax.set_xlabel("time (s)")
