"""What the runtime reports about itself: latency figures, counters, the live status line."""

from __future__ import annotations

import sys
import time
from typing import TextIO

import numpy as np

COUNTERS = ("readings", "accepted", "rejected", "before_start", "timeout", "corrupt",
            "unplugged", "reconnects", "stale_replies", "servo_errors", "deadline_misses",
            "skipped_ticks", "events")
"""The runtime's counters: readings attempted, and what became of them; ``deadline_misses``
counts samples published after their deadline (the next sample's scheduled time) plus the
ticks skipped when the loop fell a whole period behind (``skipped_ticks``)."""


class Latencies:
    """Latencies (s) of every published sample, kept in a growing float64 buffer."""

    def __init__(self, capacity: int = 1 << 16) -> None:
        self._data = np.empty(capacity)
        self.n = 0

    def add(self, latency_s: float) -> None:
        if self.n == self._data.size:
            self._data = np.concatenate((self._data, np.empty(self._data.size)))
        self._data[self.n] = latency_s
        self.n += 1

    @property
    def values_s(self) -> np.ndarray:
        return self._data[:self.n]

    def summary_ms(self) -> dict[str, float]:
        """p50, p99 and max in ms (NaN when nothing was published)."""
        if self.n == 0:
            return {"p50_ms": float("nan"), "p99_ms": float("nan"), "max_ms": float("nan")}
        v = self.values_s * 1e3
        p50, p99 = np.percentile(v, [50, 99])
        return {"p50_ms": float(p50), "p99_ms": float(p99), "max_ms": float(v.max())}


class StatusLine:
    """A one-line live status on a terminal (rewritten in place every ``every_s``)."""

    def __init__(self, stream: TextIO = sys.stderr, every_s: float = 0.5) -> None:
        self.stream, self.every_s = stream, every_s
        self._next = 0.0
        self._shown = False

    def update(self, t_s: float, labels: tuple[str, ...], values: np.ndarray | None,
               counters: dict[str, int], latencies: Latencies, force: bool = False) -> None:
        now = time.monotonic()
        if now < self._next and not force:
            return
        self._next = now + self.every_s
        rates = ""
        if values is not None:
            shown = [(lab, v) for lab, v in zip(labels, values, strict=True)
                     if lab.endswith(("_ia_pps", "_ii_pps", "_ib_pps"))]
            rates = " ".join(f"{lab[:-4]} {v:5.1f}" for lab, v in shown)
        c = counters
        lat = latencies.summary_ms()
        faults = (f"rej {c['rejected']} to {c['timeout']} bad {c['corrupt']} "
                  f"unpl {c['unplugged']} reconn {c['reconnects']}")
        line = (f"\r{t_s:7.1f}s  {rates} pps | miss {c['deadline_misses']} | {faults} | "
                f"p99 {lat['p99_ms']:.2f} ms")
        self.stream.write(line + "\x1b[K")
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()
