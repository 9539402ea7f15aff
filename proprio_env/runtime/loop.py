"""The real-time loop: one reading per sample period on an absolute schedule, the chain, the
stages, the pulse encoder, the sinks, and the figures of how well it kept time.

Sample k is due at ``t0 + k / rate_hz`` (an absolute schedule: no drift, whatever each sample
cost). Its deadline is the next sample's due time: a sample published later is a deadline
miss; when the loop falls a whole period behind (a reply timeout of tens of ms), the ticks it
can no longer read are skipped and counted as misses too (a past reading cannot be taken).

What happens to each reading (docs/runtime.md has the table):

- a failed read (timeout, corrupt reply, unplugged adapter) is logged and counted, nothing is
  pushed or published; the chain bridges the gap at its next reading, or restarts at rest
  when it exceeds ``max_bridge_s`` (its documented rules, docs/faults.md);
- the first valid reading resets the chain at rest at its angle (as
  :func:`spindle.chain.run_chain` starts); readings before it are logged ``before_start``;
- every later reading is pushed (``push_counts``) with the servo's load word beside it
  (``force_sense``, on by default: the chain's Ib; a load that was not read, -1, is an
  invalid word and the chain holds the last torque, counted ``invalid_load``); the chain
  accepts it or rejects it (out-of-range, repeated time...) by its rules and the output is
  published either way.
"""

from __future__ import annotations

import gc
import math
import os
import signal
import threading
import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from proprio_env.runtime.realtime import TtyWorkers, check_priority, set_realtime
from proprio_env.runtime.sinks import (
    ACCEPTED,
    BEFORE_START,
    ERROR,
    REJECTED,
    CsvLog,
    Layout,
    Row,
)
from proprio_env.runtime.sources import OK, Reading
from proprio_env.runtime.stages import (
    RuntimeSample,
    SpindleStage,
    check_pulse_encoder,
    check_stage,
)
from proprio_env.runtime.status import COUNTERS, Latencies, StatusLine
from spindle.backends import DEFAULT_BACKEND
from spindle.chain import ChainConfig, make_chain
from spindle.chain.sensor import is_valid_reading

SPIN_S = 2e-4
"""The last part of each wait is spent spinning: ``time.sleep`` overshoots by ~0.1 ms."""
REFRESH_SLACK_S = 1e-3
"""Looking for new tty workers (~0.1 ms) is done only when the next sample is this far off."""


class Runtime:
    """A source of readings driving the chain in real time.

    Args:
        source: a source (:mod:`proprio_env.runtime.sources`).
        rate_hz: the sample rate (default 500 Hz, the AX-12 in the seed paper).
        backend: the chain's backend, ``"numpy" | "c" | "auto"`` (default: C where it
            builds, through :func:`spindle.backends.resolve_backend`); ``self.backend`` is
            the resolved one.
        config: the chain's other settings (default ``ChainConfig()``; its ``backend`` field
            is replaced by ``backend``).
        stages: the rate stream's stages (default ``[SpindleStage()]``).
        pulse_encoder: turns each sample's rates into pulse events (None: no pulse stream).
        sinks: live sinks (LSL, callback), timed for the latency.
        log: the CSV log (None: no log).
        status: the live status line (None: silent).
        duration_s: stop after this long (None: until :meth:`stop`, a signal, or the
            source's end).
        info: extra key/values for the streams' metadata and the summary.
        rt_priority: run the loop under ``SCHED_FIFO`` at this priority (1-99; needs
            CAP_SYS_NICE, e.g. root): other work on the machine then cannot delay a sample.
            ``None``: the normal scheduler. Refused by the system: ``PermissionError``.
        tty_worker_priority: meanwhile run the kernel's workers that carry the serial
            port's bytes (:class:`~proprio_env.runtime.realtime.TtyWorkers`) under
            ``SCHED_FIFO`` at this priority (1-99, below ``rt_priority``; root); restored
            at the end. ``None``: left alone. Refused: ``PermissionError``.
        force_sense: push each reading's load word into the chain (its tendon organs' Ib);
            False pushes the angle alone (Ib stays at rest at zero force).
    """

    def __init__(self, source, *, rate_hz: float = 500.0, backend: str = DEFAULT_BACKEND,
                 config: ChainConfig | None = None,
                 stages: Sequence[object] | None = None, pulse_encoder: object | None = None,
                 sinks: Sequence[object] = (), log: CsvLog | None = None,
                 status: StatusLine | None = None, duration_s: float | None = None,
                 info: dict[str, str] | None = None, rt_priority: int | None = None,
                 force_sense: bool = True, tty_worker_priority: int | None = None) -> None:
        if not (isinstance(rate_hz, int | float) and math.isfinite(rate_hz)
                and 0 < rate_hz <= 10_000):
            raise ValueError(f"rate_hz={rate_hz!r} must be a real number in (0, 10000]")
        if duration_s is not None and not duration_s > 0:
            raise ValueError(f"duration_s={duration_s!r} must be > 0 (or None)")
        check_priority("rt_priority", rt_priority)
        check_priority("tty_worker_priority", tty_worker_priority)
        self.rt_priority, self.tty_worker_priority = rt_priority, tty_worker_priority
        self.tty_workers: TtyWorkers | None = None
        self.force_sense = bool(force_sense)
        stages = [SpindleStage()] if stages is None else list(stages)
        labels, units, self._widths = ["reading_index"], ["1"], []
        for stage in stages:
            lab, uni = check_stage(stage)
            labels += lab
            units += uni
            self._widths.append(len(lab))
        if len(set(labels)) != len(labels):
            raise ValueError(f"channel labels repeat: {labels}")
        event_fields = () if pulse_encoder is None else check_pulse_encoder(pulse_encoder)
        config = ChainConfig() if config is None else config
        self.chain = make_chain(replace(config, backend=backend))
        self.backend = self.chain.config.backend
        self.source, self.stages, self.pulse_encoder = source, stages, pulse_encoder
        self.rate_hz, self.period_s = float(rate_hz), 1.0 / float(rate_hz)
        self.sinks, self.log, self.status = list(sinks), log, status
        self.duration_s = duration_s
        meta = {"backend": self.backend, "rate_hz": repr(self.rate_hz),
                "source": type(source).__name__}
        self.layout = Layout(tuple(labels), tuple(units), event_fields, self.rate_hz,
                             {**meta, **(info or {})})
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.latencies = Latencies()
        self._stop = threading.Event()
        self._started = False

    def stop(self) -> None:
        """Ask the loop to stop after the current sample (thread- and signal-safe)."""
        self._stop.set()

    # -- the loop ------------------------------------------------------------------------------
    def run(self) -> dict[str, object]:
        """Run until stopped; flush and close everything; return :meth:`summary`."""
        scheduler = set_realtime(self.rt_priority)
        try:
            self._boost_tty_workers()
        except BaseException:
            self._restore(None, scheduler)
            raise
        previous = self._install_signals()
        gc_was_enabled = gc.isenabled()
        try:
            self.source.open()
        except BaseException:
            self._restore(previous, scheduler)
            raise
        try:
            self._open_outputs()
            gc.collect()
            gc.disable()  # a collection pause is a latency spike; the loop makes no cycles
            self._loop()
        except KeyboardInterrupt:
            pass
        finally:
            if gc_was_enabled:
                gc.enable()
            try:
                self._close()
            finally:
                self._restore(previous, scheduler)
        return self.summary()

    def _boost_tty_workers(self) -> None:
        if self.tty_worker_priority is not None:
            self.tty_workers = TtyWorkers(self.tty_worker_priority)
            self.tty_workers.boost()

    def _open_outputs(self) -> None:
        for sink in self.sinks:
            sink.open(self.layout)
        if self.log is not None:
            self.log.open(self.layout)
        bind = getattr(self.pulse_encoder, "bind", None)
        if bind is not None:
            bind(self.layout.channel_labels[1:], self.layout.units[1:])

    def _loop(self) -> None:
        period = self.period_s
        self.t0 = t0 = time.perf_counter()
        end = math.inf if self.duration_s is None else t0 + self.duration_s
        k, skipped = 0, 0
        while not self._stop.is_set():
            due = t0 + k * period
            if due >= end:
                break
            _wait_until(due)
            asked = time.perf_counter()
            try:
                reading = self.source.read()
            except StopIteration:
                break
            arrival = time.perf_counter()
            try:
                row = self._process(k, reading, arrival, due + period)
            except Exception:  # a stage or sink failed: the reading still goes in the log
                if self.log is not None:
                    self.log.write(Row(k, arrival - t0, arrival, ERROR, reading))
                raise
            row.skipped_before, row.read_s = skipped, arrival - asked
            if self.log is not None:
                self.log.write(row)
            if self.status is not None:
                self.status.update(row.t_s, self.layout.channel_labels, row.values,
                                   self.counters, self.latencies)
            k += 1
            if (self.tty_workers is not None
                    and time.perf_counter() < t0 + k * period - REFRESH_SLACK_S):
                self.tty_workers.refresh()  # in the slack before the next sample is due
            late = time.perf_counter() - (t0 + k * period)
            skipped = int(late // period) if late > period else 0
            while skipped and t0 + (k + skipped - 1) * period >= end:
                skipped -= 1  # ticks past the end of the run are not misses
            k += skipped
            self.counters["skipped_ticks"] += skipped
            self.counters["deadline_misses"] += skipped

    def _process(self, index: int, reading: Reading, arrival: float, deadline: float) -> Row:
        t_s = reading.t_s if reading.t_s is not None else arrival - self.t0
        row = Row(index, t_s, arrival, reading.status, reading)
        c = self.counters
        c["readings"] += 1
        c["servo_errors"] += int(reading.servo_error != 0)
        c["stale_replies"] += reading.stale_replies
        c["reconnects"] = getattr(self.source, "reconnects", 0)
        if reading.status != OK:
            c[reading.status] += 1
            return row
        out = self._push(t_s, reading.counts, reading.load_raw if self.force_sense else None)
        if out is None:
            row.status = BEFORE_START
            c[BEFORE_START] += 1
            return row
        row.status = ACCEPTED if out.accepted else REJECTED
        c[row.status] += 1
        sample = RuntimeSample(index, t_s, reading, out)
        values = np.empty(len(self.layout.channel_labels))
        values[0] = index
        i = 1
        for stage, n in zip(self.stages, self._widths, strict=True):
            v = np.asarray(stage.step(t_s, sample), dtype=float)
            if v.shape != (n,) or not np.all(np.isfinite(v)):
                raise ValueError(f"stage {stage!r} returned {v!r} at t_s={t_s!r}: expected "
                                 f"{n} finite values")
            values[i:i + n] = v
            i += n
        row.chain, row.values = out, values
        if self.pulse_encoder is not None:
            row.events = self._events(t_s, values[1:])
            c["events"] += len(row.events)
        for sink in self.sinks:
            sink.publish(row)
        done = time.perf_counter()
        row.latency_s = done - arrival
        self.latencies.add(row.latency_s)
        row.deadline_missed = done > deadline
        c["deadline_misses"] += int(row.deadline_missed)
        return row

    def _events(self, t_s: float, rates: np.ndarray) -> np.ndarray:
        events = self.pulse_encoder.step(t_s, rates)
        names = getattr(getattr(events, "dtype", None), "names", None) or ()
        if getattr(events, "ndim", 0) != 1 or not set(self.layout.event_fields) <= set(names):
            raise ValueError(f"pulse encoder {self.pulse_encoder!r} returned {events!r} at "
                             f"t_s={t_s!r}: expected a 1-D structured array with fields "
                             f"{self.layout.event_fields}")
        return events

    def _push(self, t_s: float, counts: int, load: int | None):
        """The chain's output for this reading (and load word), or None before its first
        valid reading (which resets the chain at rest there, as run_chain starts)."""
        if self._started:
            return self.chain.push_counts(t_s, counts, load)
        cfg = self.chain.config
        if not is_valid_reading(counts, cfg.encoder.max_count):
            return None
        self._started = True
        return self.chain.reset(float(cfg.calibration.angle_deg(counts)), t_s, load=load)

    # -- start and end -------------------------------------------------------------------------
    def _install_signals(self):
        if threading.current_thread() is not threading.main_thread():
            return None
        return signal.signal(signal.SIGTERM, lambda *_: self.stop())

    def _restore(self, previous, scheduler) -> None:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if self.tty_workers is not None:
            self.tty_workers.restore()
        if scheduler is not None:
            os.sched_setscheduler(0, *scheduler)

    def _close(self) -> None:
        try:
            self.source.close()
        finally:
            for sink in self.sinks:
                sink.close()
            if self.status is not None:
                self.status.close()
            if self.log is not None:
                self.log.close(self.summary())

    def summary(self) -> dict[str, object]:
        """Counters, the chain's counters, latency figures, the setting and the load."""
        return {"counters": dict(self.counters),
                "chain_counters": dict(self.chain.counters) if self._started else {},
                "latency": self.latencies.summary_ms(), "backend": self.backend,
                "rate_hz": self.rate_hz, "channel_labels": list(self.layout.channel_labels),
                "units": list(self.layout.units),
                "event_fields": list(self.layout.event_fields),
                "load_average": list(os.getloadavg()), "rt_priority": self.rt_priority,
                "tty_worker_priority": self.tty_worker_priority,
                "info": self.layout.info}


def _wait_until(target: float) -> None:
    """Sleep, then spin the last :data:`SPIN_S`, until ``perf_counter() >= target``."""
    remaining = target - time.perf_counter()
    if remaining > SPIN_S:
        time.sleep(remaining - SPIN_S)
    while time.perf_counter() < target:
        pass
