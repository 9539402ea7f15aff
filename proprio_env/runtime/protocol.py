"""Dynamixel Protocol 1.0 packets and the AX-12's control table (what both ends speak).

An instruction packet is ``FF FF id length instruction params... checksum`` and a status
packet ``FF FF id length error params... checksum``, with ``length`` = number of params + 2
and ``checksum = ~(id + length + instruction|error + sum(params)) & 0xFF`` (ROBOTIS e-Manual,
"Protocol 1.0"). The runtime sends its packets through ``dynamixel_sdk``; this module is what
the virtual servo parses and answers with, and what the tests check packets against.

Control-table addresses are the AX-12's (e-Manual "AX-12/AX-12A", control table): the
runtime reads present position (36, 2 bytes), present speed (38, 2) and present load (40, 2)
in one READ of 6 bytes from 36, and may write the return delay time (5; delay = 2 us x value).
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff"
BROADCAST_ID = 0xFE

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03

ERR_VOLTAGE = 0x01
ERR_ANGLE = 0x02
ERR_OVERHEAT = 0x04
ERR_RANGE = 0x08
ERR_CHECKSUM = 0x10
ERR_OVERLOAD = 0x20
ERR_INSTRUCTION = 0x40

ADDR_MODEL_NUMBER = 0
ADDR_FIRMWARE = 2
ADDR_ID = 3
ADDR_BAUD_RATE = 4
ADDR_RETURN_DELAY = 5
ADDR_CW_LIMIT = 6
ADDR_CCW_LIMIT = 8
ADDR_TORQUE_ENABLE = 24
ADDR_GOAL_POSITION = 30
ADDR_PRESENT_POSITION = 36
ADDR_PRESENT_SPEED = 38
ADDR_PRESENT_LOAD = 40
ADDR_PRESENT_VOLTAGE = 42
ADDR_PRESENT_TEMPERATURE = 43
ADDR_MOVING = 46
CONTROL_TABLE_SIZE = 50
READINGS_ADDR, READINGS_LEN = ADDR_PRESENT_POSITION, 6
"""The runtime's one read per sample: position, speed and load words, little-endian."""

AX12_MODEL_NUMBER = 12
RETURN_DELAY_US_PER_UNIT = 2.0
LOAD_DIRECTION_BIT = 1 << 10
"""Present load: bits 0-9 the magnitude (0-1023, fraction of full torque x 1023), bit 10 the
direction (set: clockwise, i.e. towards extension here)."""


def checksum(body: bytes) -> int:
    """Protocol 1.0 checksum of ``id, length, instruction|error, params...``."""
    return ~sum(body) & 0xFF


def instruction_packet(servo_id: int, instruction: int, params: bytes = b"") -> bytes:
    """An instruction packet (what ``dynamixel_sdk.PacketHandler(1.0)`` sends)."""
    body = bytes((servo_id, len(params) + 2, instruction)) + bytes(params)
    return HEADER + body + bytes((checksum(body),))


def status_packet(servo_id: int, error: int, params: bytes = b"") -> bytes:
    """A status packet (what the servo answers)."""
    body = bytes((servo_id, len(params) + 2, error)) + bytes(params)
    return HEADER + body + bytes((checksum(body),))


@dataclass(frozen=True)
class Packet:
    """A parsed packet: ``code`` is the instruction (or the error byte of a status packet);
    ``checksum_ok`` False when the received checksum did not match."""

    servo_id: int
    code: int
    params: bytes
    checksum_ok: bool


class PacketParser:
    """Splits a byte stream into packets: bytes before a header are skipped, a packet whose
    length field is impossible (< 2) is dropped with its header, and an incomplete packet
    waits for more bytes."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.skipped_bytes = 0

    def feed(self, data: bytes) -> list[Packet]:
        """Append ``data``; return every complete packet now in the buffer, in order."""
        self._buffer += data
        packets = []
        while True:
            start = self._buffer.find(HEADER)
            if start < 0:
                # a trailing 0xFF may be the first half of the next header
                keep = 1 if self._buffer.endswith(b"\xff") else 0
                self.skipped_bytes += len(self._buffer) - keep
                del self._buffer[:len(self._buffer) - keep]
                return packets
            self.skipped_bytes += start
            del self._buffer[:start]
            while self._buffer[2:3] == b"\xff":  # FF FF FF ...: the header is the last two
                del self._buffer[0]
                self.skipped_bytes += 1
            if len(self._buffer) < 4:
                return packets
            length = self._buffer[3]
            if length < 2:
                del self._buffer[:2]
                self.skipped_bytes += 2
                continue
            total = length + 4
            if len(self._buffer) < total:
                return packets
            raw = bytes(self._buffer[:total])
            del self._buffer[:total]
            body = raw[2:-1]
            packets.append(Packet(raw[2], raw[4], raw[5:-1], checksum(body) == raw[-1]))


def word(value: int) -> bytes:
    """A 16-bit little-endian word (the control table's 2-byte registers)."""
    return bytes((value & 0xFF, (value >> 8) & 0xFF))


def load_word(load_fraction: float) -> int:
    """Present load register for a signed fraction of full torque (+: counter-clockwise)."""
    magnitude = min(round(abs(load_fraction) * 1023), 1023)
    return magnitude | (LOAD_DIRECTION_BIT if load_fraction < 0 else 0)


def load_fraction(register: int) -> float:
    """Signed fraction of full torque from the present load register (inverse of
    :func:`load_word`; bits above 10 are ignored)."""
    magnitude = (register & 0x3FF) / 1023.0
    return -magnitude if register & LOAD_DIRECTION_BIT else magnitude


def speed_word(speed_rpm: float) -> int:
    """Present speed register: 0.111 rpm per unit (bits 0-9), bit 10 set when clockwise."""
    magnitude = min(round(abs(speed_rpm) / 0.111), 1023)
    return magnitude | (LOAD_DIRECTION_BIT if speed_rpm < 0 else 0)
