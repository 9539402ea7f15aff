"""Where the runtime's outputs go: Lab Streaming Layer outlets, a Python callback, and the
CSV log of every reading.

A live sink has ``open(layout)``, ``publish(row)`` and ``close()``; the loop times the live
sinks (the reading's arrival to the last live sink done is the latency it reports), then
writes the row to the :class:`CsvLog`. A :class:`Row` is one reading attempt and what came
of it.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from proprio_env.runtime.sources import Reading
from spindle.chain import MUSCLES, ArmSample
from spindle.chain.config import SCALAR_OUTPUTS

ACCEPTED, REJECTED, BEFORE_START = "accepted", "rejected", "before_start"
"""Log statuses of a reading that was read (the others are the sources' failures)."""
ERROR = "error"
"""The log status of the reading during which a stage, the pulse encoder or a sink raised
(the runtime then stops with that error, after logging the reading and closing)."""

LOOPBACK_LSL_CONFIG = """\
; liblsl kept on this machine: IPv4 loopback only, machine-scope discovery, no other peer
[ports]
IPv6 = disable
[multicast]
ResolveScope = machine
MachineAddresses = {127.0.0.1}
AddressesOverride = {127.0.0.1}
Interfaces = {127.0.0.1}
ListenAddress = 127.0.0.1
TTLOverride = 0
[lab]
KnownPeers = {127.0.0.1}
"""
"""An ``lsl_api.cfg`` that keeps LSL on the loopback (keys of liblsl's ``api_config.cpp``)."""


def write_loopback_lsl_config(path: str | Path) -> Path:
    """Write :data:`LOOPBACK_LSL_CONFIG` to ``path``; point ``LSLAPICFG`` at it before
    ``pylsl`` is first imported (liblsl reads it once per process)."""
    path = Path(path)
    path.write_text(LOOPBACK_LSL_CONFIG)
    return path


@dataclass(frozen=True)
class Layout:
    """The streams' layout: the rate channels (``reading_index`` first) and the event fields
    (empty: no pulse encoder)."""

    channel_labels: tuple[str, ...]
    units: tuple[str, ...]
    event_fields: tuple[str, ...]
    rate_hz: float
    info: dict[str, str] = field(default_factory=dict)


@dataclass
class Row:
    """One reading attempt: ``chain`` and ``values`` are None when nothing was published
    (a failed read, or before the chain's first valid reading); ``arrival_s`` is when the
    reading arrived, on ``time.perf_counter``'s clock."""

    index: int
    t_s: float
    arrival_s: float
    status: str
    reading: Reading
    chain: ArmSample | None = None
    values: np.ndarray | None = None
    events: np.ndarray | None = None
    latency_s: float = float("nan")
    read_s: float = float("nan")
    deadline_missed: bool = False
    skipped_before: int = 0


def _pylsl():
    try:
        import pylsl
    except ImportError as err:
        raise ImportError("streaming on Lab Streaming Layer needs pylsl: pip install "
                          "'proprio-elbow[runtime]'") from err
    return pylsl


class LslSink:
    """Two outlets: ``<name>-rates`` (regular, at the sample rate, float64, channel labels,
    units and types in its XML ``desc/channels``) and, with a pulse encoder,
    ``<name>-pulses`` (irregular, one sample per event, its fields as channels).

    Timestamps are the reading's arrival on LSL's clock (``local_clock``) for the rates, and
    the event's ``t_s`` mapped to that clock for the pulses. ``buffer_s`` is what liblsl
    keeps per consumer: a consumer stalled longer loses its oldest samples (liblsl's rule);
    pushing never waits for a consumer. ``wait_for_consumers_s``: at open, wait up to that
    long for a consumer of every outlet (a recorder, an experiment) before the loop starts,
    so it misses no sample (an inlet receives what is pushed after it connected).
    ``linger_s``: at close, how long connected consumers get to receive the last samples.
    """

    def __init__(self, name: str = "proprio", source_id: str = "proprio-elbow",
                 buffer_s: int = 360, wait_for_consumers_s: float = 0.0,
                 linger_s: float = 0.5) -> None:
        if not (isinstance(buffer_s, int) and buffer_s >= 1):
            raise ValueError(f"buffer_s={buffer_s!r} must be an integer >= 1 (seconds)")
        self.name, self.source_id, self.buffer_s = name, source_id, buffer_s
        self.wait_for_consumers_s = float(wait_for_consumers_s)
        self.linger_s = float(linger_s)
        self.rates = self.pulses = None

    def open(self, layout: Layout) -> None:
        lsl = _pylsl()
        info = lsl.StreamInfo(f"{self.name}-rates", "Proprioception",
                              len(layout.channel_labels), layout.rate_hz, lsl.cf_double64,
                              f"{self.source_id}-rates")
        self._describe(info, layout.channel_labels, layout.units, layout.info)
        self.rates = lsl.StreamOutlet(info, 1, self.buffer_s)
        if layout.event_fields:
            info = lsl.StreamInfo(f"{self.name}-pulses", "Pulses", len(layout.event_fields),
                                  lsl.IRREGULAR_RATE, lsl.cf_double64,
                                  f"{self.source_id}-pulses")
            units = tuple("s" if f == "t_s" else "" for f in layout.event_fields)
            self._describe(info, layout.event_fields, units, layout.info)
            self.pulses = lsl.StreamOutlet(info, 1, self.buffer_s)
        self._fields = layout.event_fields
        for outlet in (self.rates, self.pulses):
            if outlet is not None and self.wait_for_consumers_s > 0:
                outlet.wait_for_consumers(self.wait_for_consumers_s)
        # LSL's clock and perf_counter are both the monotonic clock here; the offset maps
        # one to the other wherever they differ
        self._offset = lsl.local_clock() - time.perf_counter()

    @staticmethod
    def _describe(info, labels, units, extra) -> None:
        desc = info.desc()
        channels = desc.append_child("channels")
        for label, unit in zip(labels, units, strict=True):
            ch = channels.append_child("channel")
            ch.append_child_value("label", label)
            ch.append_child_value("unit", unit)
            ch.append_child_value("type", "index" if label == "reading_index" else "rate")
        acquisition = desc.append_child("acquisition")
        for key, value in extra.items():
            acquisition.append_child_value(key, value)

    def publish(self, row: Row) -> None:
        if row.values is None:
            return
        stamp = row.arrival_s + self._offset
        self.rates.push_sample(row.values, stamp)
        if self.pulses is not None and row.events is not None and row.events.size:
            shift = stamp - row.t_s
            for event in row.events:
                values = [float(event[f]) for f in self._fields]
                self.pulses.push_sample(values, float(event["t_s"]) + shift)

    def close(self) -> None:
        # liblsl sends from its own threads and an outlet released at once drops what it has
        # not sent yet: with consumers connected, let them have the last samples first
        if any(o is not None and o.have_consumers() for o in (self.rates, self.pulses)):
            time.sleep(self.linger_s)
        self.rates = self.pulses = None  # the outlets close when released


class CallbackSink:
    """Calls ``callback(row)`` for every published sample (not for failed reads); it runs
    inside the loop, so its time counts in the latency and may miss deadlines."""

    def __init__(self, callback: Callable[[Row], object]) -> None:
        self.callback = callback

    def open(self, layout: Layout) -> None:
        self.layout = layout

    def publish(self, row: Row) -> None:
        if row.values is not None:
            self.callback(row)

    def close(self) -> None:
        pass


_CHAIN_FIELDS = [f.name for f in fields(ArmSample) if f.name not in ("t_s", "counts")]


def _chain_columns() -> list[str]:
    out = []
    for name in _CHAIN_FIELDS:
        if name == "accepted" or name in SCALAR_OUTPUTS:
            out.append(name)
        else:
            out.extend(f"{m}_{name}" for m in MUSCLES)
    return out


def _take(text: io.StringIO) -> bytes:
    """The text written so far, as bytes, and the buffer emptied."""
    data = text.getvalue().encode()
    text.seek(0)
    text.truncate()
    return data


class _FileWriter:
    """A thread that writes byte chunks to files, so that a write that blocks in the kernel
    (a full page cache, the filesystem's journal: measured up to 6.9 ms on this machine)
    never holds up the loop. The thread drops to the lowest real-time priority when the
    loop is real-time: it then never competes with the loop for a CPU, yet is not held off
    a CPU by ordinary processes while it holds Python's GIL (the loop would wait for it).
    An error of the thread is raised by the next :meth:`check` or :meth:`close`."""

    def __init__(self) -> None:
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="csv-log-writer", daemon=True)
        self._thread.start()

    def put(self, file, data: bytes) -> None:
        if data:
            self._queue.put((file, data))

    def _run(self) -> None:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):  # this thread only
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        while (item := self._queue.get()) is not None:
            if self._error is None:
                try:
                    item[0].write(item[1])
                    item[0].flush()
                except BaseException as err:  # kept for close(); later chunks are dropped
                    self._error = err

    def check(self) -> None:
        if self._error is not None:
            raise self._error

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join()
        self.check()


class CsvLog:
    """Every reading attempt, one CSV row each, in order: its status, the reading, the
    chain's output, the rate channels, the latency; pulse events in ``<stem>_events.csv``
    and, at :meth:`close`, the run's summary in ``<stem>_summary.json``.

    Rows are formatted in memory and handed every ``flush_every`` rows (and at the end) to
    a writer thread, which writes them to the file: the loop never waits for the disk.

    Floats are written with ``repr`` (they read back to the same float64); a failed read's
    reading and output fields are empty.
    """

    HEAD = ("index", "t_s", "status", "counts", "speed_raw", "load_raw", "load_fraction",
            "servo_error", "stale_replies", "skipped_before", "deadline_missed", "read_s",
            "latency_s", "n_events")

    def __init__(self, path: str | Path, flush_every: int = 500) -> None:
        self.path = Path(path)
        self.events_path = self.path.with_name(self.path.stem + "_events.csv")
        self.summary_path = self.path.with_name(self.path.stem + "_summary.json")
        self.flush_every = int(flush_every)
        self.rows = 0

    def open(self, layout: Layout) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._text = io.StringIO()
        self._csv = csv.writer(self._text)
        self._n_values = len(layout.channel_labels) - 1
        self._n_chain = len(_chain_columns())
        self._csv.writerow(self.HEAD + tuple(_chain_columns()) + layout.channel_labels[1:])
        self._fields = layout.event_fields
        self._events = None
        if self._fields:
            self._events_file = open(self.events_path, "wb")
            self._events_text = io.StringIO()
            self._events = csv.writer(self._events_text)
            self._events.writerow(("index", *self._fields))
        self._writer = _FileWriter()

    def write(self, row: Row) -> None:
        r = row.reading
        read = r.counts >= 0 or r.load_raw >= 0
        head = [row.index, repr(row.t_s), row.status,
                r.counts if read else "", r.speed_raw if read else "",
                r.load_raw if read else "", repr(r.load_fraction) if read else "",
                r.servo_error, r.stale_replies, row.skipped_before, int(row.deadline_missed),
                repr(row.read_s),
                "" if row.latency_s != row.latency_s else repr(row.latency_s),
                0 if row.events is None else len(row.events)]
        if row.chain is None:
            tail = [""] * (self._n_chain + self._n_values)
        else:
            tail = self._chain_values(row.chain) + [repr(float(v)) for v in row.values[1:]]
        self._csv.writerow(head + tail)
        if self._events is not None and row.events is not None:
            for event in row.events:
                self._events.writerow([row.index] + [repr(float(event[f])) for f in self._fields])
        self.rows += 1
        if self.rows % self.flush_every == 0:
            self.flush()

    @staticmethod
    def _chain_values(s: ArmSample) -> list[str]:
        out: list[str] = []
        for name in _CHAIN_FIELDS:
            value = getattr(s, name)
            if name == "accepted":
                out.append(str(int(value)))
            elif np.ndim(value) == 0:
                out.append(repr(float(value)))
            else:
                out.extend(repr(float(v)) for v in value)
        return out

    def flush(self) -> None:
        """Hand the rows written since the last flush to the writer thread; raises the
        error of an earlier write (a full disk) if one failed."""
        self._writer.check()
        self._writer.put(self._file, _take(self._text))
        if self._events is not None:
            self._writer.put(self._events_file, _take(self._events_text))

    def close(self, summary: dict | None = None) -> None:
        try:
            self.flush()
        finally:
            try:
                self._writer.close()
                os.fsync(self._file.fileno())
            finally:  # an error is already on its way up; closing can only repeat it
                with contextlib.suppress(OSError):
                    self._file.close()
                if self._events is not None:
                    with contextlib.suppress(OSError):
                        self._events_file.close()
        if summary is not None:
            self.summary_path.write_text(json.dumps(summary, indent=2, sort_keys=True))
