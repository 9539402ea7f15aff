"""A virtual Dynamixel AX-12 on a pseudo-terminal: the runtime's test fixture, and the way to
try the runtime without hardware.

It answers Protocol 1.0 (:mod:`proprio_env.runtime.protocol`) PING, READ and WRITE on the
master side of a pty whose slave a symlink (``link``) names; ``dynamixel_sdk.PortHandler``
opens the link like ``/dev/ttyUSB0`` (pyserial opens any tty path; a pty takes every baud
rate the SDK accepts and ignores it). Before answering it waits the return delay time of its
control table (register 5, 2 us per unit, factory 250 = 0.5 ms).

Its shaft follows a :class:`~proprio_env.runtime.motion.ServoTrack` from the moment it
starts serving; present position is the :class:`~proprio_env.body.encoder.Encoder` model's
reading (noise, and its glitches: an invalid reading -1 is sent as 0xFFFF, a corrupted word
as is), present speed the track's, present load the track's torque.

Faults on request (:class:`Fault`, ``--fault`` on the command line), counted by READ of the
readings (36): ``checksum`` (the reply's checksum is wrong), ``drop`` (no reply: the runtime
times out), ``range`` (position 0x0500 = 1280 counts, beyond the AX-12's 1023), ``unplug``
(the pty closes and the link disappears, as a USB adapter pulled out; a new pty and link come
back ``duration_s`` later). Every reply is recorded (:attr:`VirtualServo.replies`, and
``--record`` CSV) so a test can check that the runtime's log misses none.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import gc
import os
import select
import signal
import sys
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

from proprio_env.body.encoder import Encoder
from proprio_env.runtime import protocol as p
from proprio_env.runtime.motion import TRACKS, ServoTrack, make_track

FAULT_KINDS = ("checksum", "drop", "range", "unplug")
OUT_OF_RANGE_WORD = 0x0500
SPIN_S = 2e-4


@dataclass(frozen=True)
class Fault:
    """``kind`` on the ``at_read``-th READ of the readings (0-based) and the ``count - 1``
    after it; ``unplug`` lasts ``duration_s`` instead."""

    kind: str
    at_read: int
    count: int = 1
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"fault kind {self.kind!r} is not one of {FAULT_KINDS}")
        if self.at_read < 0 or self.count < 1:
            raise ValueError(f"fault at_read={self.at_read!r} must be >= 0 and "
                             f"count={self.count!r} >= 1")
        if self.kind == "unplug" and not self.duration_s > 0:
            raise ValueError(f"an unplug needs duration_s > 0, got {self.duration_s!r}")

    @classmethod
    def parse(cls, spec: str) -> Fault:
        """``KIND@N`` (the N-th read), ``KIND@NxK`` (K reads from it), ``unplug@N:SECONDS``."""
        try:
            kind, rest = spec.split("@")
            duration = 0.0
            if ":" in rest:
                rest, d = rest.split(":")
                duration = float(d)
            at, _, count = rest.partition("x")
            return cls(kind, int(at), int(count) if count else 1, duration)
        except ValueError as err:
            raise ValueError(f"fault {spec!r}: expected KIND@N, KIND@NxK or unplug@N:SECONDS "
                             f"with KIND in {FAULT_KINDS} ({err})") from None


def control_table(servo_id: int, return_delay: int) -> bytearray:
    """An AX-12's control table after power-on (the registers the runtime touches)."""
    table = bytearray(p.CONTROL_TABLE_SIZE)
    table[p.ADDR_MODEL_NUMBER:p.ADDR_MODEL_NUMBER + 2] = p.word(p.AX12_MODEL_NUMBER)
    table[p.ADDR_FIRMWARE] = 24
    table[p.ADDR_ID] = servo_id
    table[p.ADDR_BAUD_RATE] = 1  # 2 Mbps / (1 + 1) = 1 Mbps
    table[p.ADDR_RETURN_DELAY] = return_delay
    table[p.ADDR_CCW_LIMIT:p.ADDR_CCW_LIMIT + 2] = p.word(1023)
    table[p.ADDR_PRESENT_VOLTAGE] = 120
    table[p.ADDR_PRESENT_TEMPERATURE] = 32
    return table


class VirtualServo:
    """One AX-12 answering on a pty linked at ``link``.

    Args:
        link: path of the symlink to the pty's slave (what the runtime opens).
        track: the shaft's motion.
        servo_id: its ID (register 3).
        return_delay: register 5 at power-on (units of 2 us).
        faults: the faults to inject.
        seed: seed of the encoder model's randomness.
        ideal: readings without noise or glitches (quantisation only).
    """

    def __init__(self, link: str | Path, track: ServoTrack, servo_id: int = 1,
                 return_delay: int = 250, faults: tuple[Fault, ...] = (), seed: int = 0,
                 ideal: bool = False) -> None:
        if not 0 <= servo_id < p.BROADCAST_ID:
            raise ValueError(f"servo_id={servo_id!r} must lie in 0..{p.BROADCAST_ID - 1}")
        if not 0 <= return_delay <= 254:
            raise ValueError(f"return_delay={return_delay!r} must lie in 0..254 (2 us units)")
        self.link = Path(link)
        self.track = track
        self.table = control_table(servo_id, return_delay)
        self.faults = tuple(faults)
        encoder = Encoder(rng=seed)
        self.encoder = Encoder(encoder.params.ideal(), rng=seed) if ideal else encoder
        self.reads = 0
        self.replies: list[tuple[int, float, int, int, str]] = []
        """(read index, monotonic time, position word, load word, fault) of every READ."""
        self._master = self._slave = -1
        self._parser = p.PacketParser()
        self._t0 = time.monotonic()
        self._received = time.perf_counter()
        self._stop = False
        self.serving = threading.Event()
        """Set while :meth:`serve` answers (after the collector is off), clear otherwise."""

    # -- the pty -----------------------------------------------------------------------------
    def plug(self) -> None:
        """Open a new pty and point the link at its slave (atomically)."""
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing before the runtime configures it
        tmp = self.link.with_name(self.link.name + ".tmp")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        os.symlink(os.ttyname(self._slave), tmp)
        os.replace(tmp, self.link)
        self._parser = p.PacketParser()

    def unplug(self) -> None:
        """Close the pty and remove the link (the runtime's reads fail, its open fails)."""
        with contextlib.suppress(FileNotFoundError):
            self.link.unlink()
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def stop(self) -> None:
        self._stop = True

    # -- serving -----------------------------------------------------------------------------
    def serve(self, duration_s: float | None = None) -> None:
        """Answer packets until :meth:`stop` (or ``duration_s``); the track's time starts now.

        The garbage collector is off meanwhile: a full collection in this process (MuJoCo
        and numpy loaded) took 26 ms, once in ~20 s of serving at 500 Hz, and the reply
        waiting behind it timed out; serving makes no reference cycles."""
        if self._master < 0:
            self.plug()
        gc_was_enabled = gc.isenabled()
        gc.collect()  # a full collection of a loaded process can take longer than a read
        gc.freeze()  # what is there now is never looked at again
        gc.disable()
        # The clock starts after the collection, so neither the track nor the duration
        # loses the time it took.
        self._t0 = time.monotonic()
        end = None if duration_s is None else self._t0 + duration_s
        self.serving.set()
        try:
            while not self._stop and (end is None or time.monotonic() < end):
                ready, _, _ = select.select([self._master], [], [], 0.05)
                if not ready:
                    continue
                try:
                    data = os.read(self._master, 512)
                except OSError:  # no slave open (EIO): wait for the runtime to open it
                    time.sleep(0.001)
                    continue
                self._received = time.perf_counter()
                for packet in self._parser.feed(data):
                    self._answer(packet)
        finally:
            self.serving.clear()
            if gc_was_enabled:
                gc.enable()
            gc.unfreeze()
            self.unplug()

    def _answer(self, packet: p.Packet) -> None:
        sid = self.table[p.ADDR_ID]
        if packet.servo_id not in (sid, p.BROADCAST_ID):
            return
        if not packet.checksum_ok:
            self._reply(p.status_packet(sid, p.ERR_CHECKSUM), packet.servo_id)
            return
        if packet.code == p.INST_PING:
            self._reply(p.status_packet(sid, 0), packet.servo_id)
        elif packet.code == p.INST_READ and len(packet.params) == 2:
            self._read(packet, sid)
        elif packet.code == p.INST_WRITE and len(packet.params) >= 2:
            addr, data = packet.params[0], packet.params[1:]
            if addr + len(data) > p.CONTROL_TABLE_SIZE:
                self._reply(p.status_packet(sid, p.ERR_RANGE), packet.servo_id)
                return
            self.table[addr:addr + len(data)] = data
            self._reply(p.status_packet(sid, 0), packet.servo_id)
        else:
            self._reply(p.status_packet(sid, p.ERR_INSTRUCTION), packet.servo_id)

    def _read(self, packet: p.Packet, sid: int) -> None:
        addr, length = packet.params
        if addr + length > p.CONTROL_TABLE_SIZE:
            self._reply(p.status_packet(sid, p.ERR_RANGE), packet.servo_id)
            return
        fault = ""
        if addr <= p.ADDR_PRESENT_POSITION < addr + length:
            fault = self._fault_now()
            if fault == "unplug":
                return
            self._sample(fault)
        reply = p.status_packet(sid, 0, bytes(self.table[addr:addr + length]))
        if fault == "checksum":
            reply = reply[:-1] + bytes(((reply[-1] + 1) & 0xFF,))
        if fault != "drop":
            self._reply(reply, packet.servo_id)

    def _fault_now(self) -> str:
        """The fault of this read (and advance the read counter); an unplug happens here."""
        i = self.reads
        self.reads += 1
        for f in self.faults:
            if f.kind == "unplug" and f.at_read == i:
                self.replies.append((i, time.monotonic(), -1, -1, "unplug"))
                self.unplug()
                time.sleep(f.duration_s)
                self.plug()
                return "unplug"
            if f.kind != "unplug" and f.at_read <= i < f.at_read + f.count:
                return f.kind
        return ""

    def _sample(self, fault: str) -> None:
        now = time.monotonic()
        angle, speed_deg_s, load = self.track.at(now - self._t0)
        position = int(self.encoder.read(angle)) & 0xFFFF
        if fault == "range":
            position = OUT_OF_RANGE_WORD
        t = self.table
        t[p.ADDR_PRESENT_POSITION:p.ADDR_PRESENT_POSITION + 2] = p.word(position)
        t[p.ADDR_PRESENT_SPEED:p.ADDR_PRESENT_SPEED + 2] = p.word(
            p.speed_word(speed_deg_s / 6.0))
        t[p.ADDR_PRESENT_LOAD:p.ADDR_PRESENT_LOAD + 2] = p.word(p.load_word(load))
        t[p.ADDR_MOVING] = int(abs(speed_deg_s) > 1.0)
        self.replies.append((self.reads - 1, now, position, p.load_word(load), fault))

    def _reply(self, packet: bytes, to_id: int) -> None:
        if to_id == p.BROADCAST_ID:
            return  # a broadcast gets no status packet
        # the delay runs from the instruction's arrival (the reply was made meanwhile), the
        # last SPIN_S of it spinning: time.sleep alone overshoots by ~0.1 ms
        delay_s = self.table[p.ADDR_RETURN_DELAY] * p.RETURN_DELAY_US_PER_UNIT * 1e-6
        send_at = self._received + delay_s
        remaining = send_at - time.perf_counter()
        if remaining > SPIN_S:
            time.sleep(remaining - SPIN_S)
        while time.perf_counter() < send_at:
            pass
        with contextlib.suppress(OSError):
            os.write(self._master, packet)

    def write_record(self, path: str | Path) -> None:
        """Every READ of the readings as CSV: read, t_s (monotonic), position, load, fault."""
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(("read", "t_monotonic_s", "position", "load", "fault"))
            w.writerows(self.replies)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="proprio-virtual-servo",
        description="A virtual Dynamixel AX-12 (Protocol 1.0) on a pseudo-terminal.")
    ap.add_argument("--link", default="/tmp/proprio-ax12",
                    help="symlink to the pty (give it to proprio-run --port)")
    ap.add_argument("--id", type=int, default=1, help="servo ID (register 3)")
    ap.add_argument("--return-delay", type=int, default=250,
                    help="return delay time register at power-on (2 us units; AX-12: 250)")
    ap.add_argument("--track", choices=TRACKS, default="elbow",
                    help="scripted: the demo's command as the angle; elbow: the MuJoCo elbow "
                         "driven by it")
    ap.add_argument("--seed", type=int, default=0, help="seed of the encoder noise")
    ap.add_argument("--ideal", action="store_true", help="no noise or glitches")
    ap.add_argument("--fault", action="append", default=[], type=Fault.parse,
                    help="KIND@N[xK] or unplug@N:SECONDS; KIND: " + ", ".join(FAULT_KINDS))
    ap.add_argument("--duration", type=float, default=None, help="stop after S seconds")
    ap.add_argument("--record", default=None, help="CSV of every READ answered")
    ap.add_argument("--rt-priority", type=int, default=None,
                    help="serve under SCHED_FIFO at this priority (1-99; needs root)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    servo = VirtualServo(args.link, make_track(args.track), args.id, args.return_delay,
                         tuple(args.fault), args.seed, args.ideal)
    signal.signal(signal.SIGTERM, lambda *_: servo.stop())
    if args.rt_priority is not None:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt_priority))
    servo.plug()
    print(f"virtual AX-12 id {args.id} on {args.link} -> {os.ttyname(servo._slave)}",
          file=sys.stderr, flush=True)
    try:
        servo.serve(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        if args.record:
            servo.write_record(args.record)
    return 0


if __name__ == "__main__":
    sys.exit(main())
