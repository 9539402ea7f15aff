"""Where the runtime's readings come from: a Dynamixel servo (or the virtual one) through
``dynamixel_sdk``, a simulated elbow, or a replay of a recorded CSV.

Every source has ``open()``, ``read() -> Reading`` (one reading, now) and ``close()``; a
source that ends (a replay) raises :class:`StopIteration` from ``read``. A reading's
``status`` says what happened: :data:`OK` (a position and a load), or a failure the loop
logs and counts (:data:`TIMEOUT`, :data:`CORRUPT`, :data:`UNPLUGGED`). Whether the chain
accepted an OK reading is the loop's business.
"""

from __future__ import annotations

import csv
import math
import os
import select
import time
from dataclasses import dataclass
from pathlib import Path

from proprio_env.runtime import protocol as p

OK, TIMEOUT, CORRUPT, UNPLUGGED = "ok", "timeout", "corrupt", "unplugged"
READ_STATUSES = (OK, TIMEOUT, CORRUPT, UNPLUGGED)
BAUD_RATES = (9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
              1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000)
"""What ``dynamixel_sdk.PortHandler.setBaudRate`` accepts (others fail there)."""
PING_ATTEMPTS = 5


@dataclass(frozen=True)
class Reading:
    """One reading attempt.

    Attributes:
        status: one of :data:`READ_STATUSES`.
        counts: present position (counts; -1 when nothing was read).
        load_raw: present load register (0-2047; -1 when nothing was read).
        speed_raw: present speed register (-1 when nothing was read).
        servo_error: the status packet's error byte (0 when none).
        t_s: the reading's own time (s) when the source has one (a replay); ``None``: the
            loop stamps the arrival time.
        stale_replies: late replies to an earlier request that came before this one's and
            were dropped (see :class:`DynamixelSource`).
    """

    status: str
    counts: int = -1
    load_raw: int = -1
    speed_raw: int = -1
    servo_error: int = 0
    t_s: float | None = None
    stale_replies: int = 0

    @property
    def load_fraction(self) -> float:
        """Signed fraction of the servo's full torque (0.0 when nothing was read)."""
        return p.load_fraction(self.load_raw) if self.load_raw >= 0 else 0.0


def _sdk():
    try:
        import dynamixel_sdk
    except ImportError as err:
        raise ImportError("reading a Dynamixel servo needs dynamixel_sdk: pip install "
                          "'proprio-elbow[runtime]'") from err
    return dynamixel_sdk


class DynamixelSource:
    """An AX-12 (or the virtual one) on a serial port, read through ``dynamixel_sdk``
    (``PortHandler``, ``PacketHandler(1.0)``): one READ of 6 bytes from 36 per sample.

    Args:
        port: the serial device (``/dev/ttyUSB0``, ``/dev/ttyACM0``, the virtual servo's link).
        baud_rate: the bus rate (AX-12 factory setting: 1 Mbps); one of :data:`BAUD_RATES`.
        servo_id: the servo's ID (factory: 1).
        return_delay_us: written to register 5 on open (2 us units, rounded); ``None`` leaves
            the servo's setting (factory 500 us).
        latency_timer_ms: the USB adapter's latency timer, which ``dynamixel_sdk`` budgets
            twice into every reply timeout (timeout = bytes x 10 bits / baud + 2 x latency +
            2 ms). The SDK assumes FTDI's default, 16 ms (a 34 ms timeout); set the adapter's
            ``/sys/bus/usb-serial/devices/ttyUSB0/latency_timer`` to 1 and pass 1 here.
        reconnect_s: while unplugged, the shortest interval between two attempts to reopen.

    Protocol 1.0 status packets carry no sequence number, so a reply that comes after its
    timeout would be taken for the answer to the next request (a reading one sample old,
    silently). After a failed read the next good reply is therefore not trusted at once: the
    source waits one reply timeout more for a second packet and, if one comes, keeps that
    one and counts the first as stale (``Reading.stale_replies``). The line keeps its order,
    so the late reply always comes first.
    """

    def __init__(self, port: str, baud_rate: int = 1_000_000, servo_id: int = 1,
                 return_delay_us: float | None = None, latency_timer_ms: float = 16.0,
                 reconnect_s: float = 0.1) -> None:
        if baud_rate not in BAUD_RATES:
            raise ValueError(f"baud_rate={baud_rate!r} is not one the SDK accepts: "
                             f"{BAUD_RATES}")
        if not (isinstance(servo_id, int) and 0 <= servo_id < p.BROADCAST_ID):
            raise ValueError(f"servo_id={servo_id!r} must be an integer in 0..253")
        if return_delay_us is not None and not 0 <= return_delay_us <= 508:
            raise ValueError(f"return_delay_us={return_delay_us!r} must lie in 0..508 us")
        if not (math.isfinite(latency_timer_ms) and latency_timer_ms >= 0):
            raise ValueError(f"latency_timer_ms={latency_timer_ms!r} must be finite and >= 0")
        self.port_name = str(port)
        self.baud_rate = baud_rate
        self.servo_id = servo_id
        self.return_delay_us = return_delay_us
        self.latency_timer_ms = float(latency_timer_ms)
        self.reconnect_s = float(reconnect_s)
        self.reconnects = 0
        self._sdk = _sdk()
        self._packets = self._sdk.PacketHandler(1.0)
        self._port = None
        self._next_attempt = 0.0
        self._suspect = False  # the last read failed: a late reply may still come

    def _port_handler(self):
        """A ``PortHandler`` whose reply timeout budgets this adapter's latency timer, and
        whose reads wait for bytes in ``select`` instead of polling: the SDK's receive loop
        polls a non-blocking port, which keeps a core busy and, on a loaded 2-core machine,
        delays the very process (or kernel worker) that brings the reply (measured against
        the virtual servo: p90 of a read 8.1 ms polling, 0.54 ms waiting)."""
        latency_ms = self.latency_timer_ms

        class Port(self._sdk.PortHandler):
            def setPacketTimeout(self, packet_length):
                self.packet_start_time = self.getCurrentTime()
                self.packet_timeout = self.tx_time_per_byte * packet_length + 2 * latency_ms + 2

            def readPort(self, length):
                if self.ser.in_waiting == 0:
                    left_s = (self.packet_timeout - self.getTimeSinceStart()) * 1e-3
                    if left_s > 0:
                        select.select([self.ser.fileno()], [], [], left_s)
                return self.ser.read(length)

        return Port(self.port_name)

    def open(self) -> None:
        """Open the port and check the servo answers (PING); raises ``OSError`` when not."""
        port = self._port_handler()
        try:
            if not (port.openPort() and port.setBaudRate(self.baud_rate)):
                raise OSError(f"cannot open {self.port_name} at {self.baud_rate} baud")
            for _ in range(PING_ATTEMPTS):  # the first reply after opening may be slow
                model, result, _ = self._packets.ping(port, self.servo_id)
                if result == 0:
                    break
            if result != 0:
                raise OSError(f"no servo id {self.servo_id} on {self.port_name}: "
                              f"{self._packets.getTxRxResult(result)}")
            if self.return_delay_us is not None:
                value = round(self.return_delay_us / p.RETURN_DELAY_US_PER_UNIT)
                result, _ = self._packets.write1ByteTxRx(port, self.servo_id,
                                                         p.ADDR_RETURN_DELAY, value)
                if result != 0:
                    raise OSError(f"cannot write the return delay: "
                                  f"{self._packets.getTxRxResult(result)}")
        except Exception as err:
            if port.is_open:
                port.closePort()
            raise OSError(str(err)) from err
        self.model_number = model
        self._port = port

    def read(self) -> Reading:
        if self._port is None and not self._reconnect():
            return Reading(UNPLUGGED)
        try:
            data, result, error = self._packets.readTxRx(
                self._port, self.servo_id, p.READINGS_ADDR, p.READINGS_LEN)
        except Exception:  # the adapter went away (pyserial's SerialException, EIO)
            self._drop_port()
            return Reading(UNPLUGGED)
        ok = result == self._sdk.COMM_SUCCESS and len(data) == p.READINGS_LEN
        stale = 0
        if ok and self._suspect:
            data, error, stale = self._newest_reply(data, error)
        self._suspect = not ok
        if result == self._sdk.COMM_RX_TIMEOUT:
            return Reading(TIMEOUT, servo_error=error)
        if not ok:
            return Reading(CORRUPT, servo_error=error)
        return Reading(OK, data[0] | data[1] << 8, data[4] | data[5] << 8,
                       data[2] | data[3] << 8, error, stale_replies=stale)

    def _newest_reply(self, data: list[int], error: int) -> tuple[list[int], int, int]:
        """After a failed read: a second reply within one timeout means the first was the
        late answer to the failed request."""
        try:
            self._port.setPacketTimeout(p.READINGS_LEN + 6)
            newer, result, newer_error = self._packets.readRx(
                self._port, self.servo_id, p.READINGS_LEN)
        except Exception:  # the port went away: keep what came; the next read notices
            return data, error, 0
        if result == self._sdk.COMM_SUCCESS and len(newer) == p.READINGS_LEN:
            return newer, newer_error, 1
        return data, error, 0

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        try:
            port.closePort()
        except Exception:  # closing a vanished device may fail too; it is gone either way
            pass
        self._next_attempt = time.monotonic() + self.reconnect_s

    def _reconnect(self) -> bool:
        now = time.monotonic()
        if now < self._next_attempt or not os.path.exists(self.port_name):
            return False
        try:
            self.open()
        except OSError:
            self._next_attempt = now + self.reconnect_s
            return False
        self.reconnects += 1
        return True

    def close(self) -> None:
        if self._port is not None:
            self._drop_port()


class SimulatedElbowSource:
    """The MuJoCo elbow in process: a :class:`~proprio_env.runtime.motion.ServoTrack` read by
    the encoder model at the moment of each read (time from :meth:`open`)."""

    def __init__(self, track: str = "elbow", seed: int = 0) -> None:
        from proprio_env.body.encoder import Encoder
        from proprio_env.runtime.motion import make_track

        self.track = make_track(track)
        self.encoder = Encoder(rng=seed)
        self._t0 = time.monotonic()

    def open(self) -> None:
        self._t0 = time.monotonic()

    def read(self) -> Reading:
        angle, speed_deg_s, load = self.track.at(time.monotonic() - self._t0)
        counts = int(self.encoder.read(angle)) & 0xFFFF
        return Reading(OK, counts, p.load_word(load), p.speed_word(speed_deg_s / 6.0))

    def close(self) -> None:
        pass


class ReplaySource:
    """Readings recorded in a CSV (a runtime log, or any file with ``t_s`` and ``counts``
    columns, optionally ``load_raw`` and ``status``), fed in order with their own times.

    Rows whose ``status`` is a failed read are replayed as that failure; an empty ``counts``
    is a failed read too.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with open(self.path, newline="") as f:
            reader = csv.DictReader(f)
            missing = {"t_s", "counts"} - set(reader.fieldnames or ())
            if missing:
                raise ValueError(f"{self.path}: no column {sorted(missing)} (need t_s, counts)")
            self._rows = [self._reading(r, i + 2) for i, r in enumerate(reader)]
        self._next = 0

    def _reading(self, row: dict[str, str], line: int) -> Reading:
        status = row.get("status") or OK
        if status not in READ_STATUSES:  # a runtime log's accepted/rejected: both were read
            status = OK
        try:
            t = float(row["t_s"])
            if status != OK or row["counts"] == "":
                return Reading(status if status != OK else CORRUPT, t_s=t)
            return Reading(OK, int(float(row["counts"])), int(float(row.get("load_raw") or -1)),
                           int(float(row.get("speed_raw") or -1)), t_s=t)
        except ValueError as err:
            raise ValueError(f"{self.path}:{line}: {err}") from None

    def open(self) -> None:
        self._next = 0

    def read(self) -> Reading:
        if self._next >= len(self._rows):
            raise StopIteration
        self._next += 1
        return self._rows[self._next - 1]

    def close(self) -> None:
        pass
