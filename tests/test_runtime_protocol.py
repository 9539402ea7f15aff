"""Protocol 1.0 packets against the ROBOTIS e-Manual's worked examples and the SDK's own
packets; the virtual servo's answers through dynamixel_sdk."""

from __future__ import annotations

import threading

import pytest

from proprio_env.runtime import protocol as p
from proprio_env.runtime.virtual_servo import Fault


def test_packets_match_the_manuals_examples():
    # e-Manual, Protocol 1.0, "READ DATA": read the internal temperature (0x2B, 1 byte) of
    # ID 1, and its status packet reporting 32 degrees
    assert p.instruction_packet(1, p.INST_READ, bytes((0x2B, 0x01))) == bytes.fromhex(
        "FFFF0104022B01CC")
    assert p.status_packet(1, 0, bytes((0x20,))) == bytes.fromhex("FFFF01030020DB")


def test_the_parser_splits_a_noisy_stream():
    a = p.instruction_packet(1, p.INST_READ, bytes((36, 6)))
    b = p.instruction_packet(1, p.INST_PING)
    bad = a[:-1] + bytes(((a[-1] + 1) & 0xFF,))
    parser = p.PacketParser()
    stream = b"\x00\x13" + a + b"\xff" + bad + b[:3]
    packets = parser.feed(stream)
    assert [(q.servo_id, q.code, q.params, q.checksum_ok) for q in packets] == [
        (1, p.INST_READ, bytes((36, 6)), True), (1, p.INST_READ, bytes((36, 6)), False)]
    assert parser.feed(b[3:]) == [p.Packet(1, p.INST_PING, b"", True)]
    assert parser.skipped_bytes == 3


def test_load_and_speed_words_follow_the_ax12_table():
    # AX-12 control table: 0-1023 counter-clockwise, 1024-2047 clockwise (bit 10)
    assert p.load_word(1.0) == 1023 and p.load_word(-1.0) == 2047 and p.load_word(0.0) == 0
    assert p.load_fraction(1024 + 512) == pytest.approx(-512 / 1023)
    assert p.speed_word(-0.111 * 100) == 1024 + 100


def test_fault_specs_parse_or_say_why():
    assert Fault.parse("drop@12x3") == Fault("drop", 12, 3)
    assert Fault.parse("unplug@5:0.25") == Fault("unplug", 5, 1, 0.25)
    with pytest.raises(ValueError, match="fault 'melt@3'"):
        Fault.parse("melt@3")
    with pytest.raises(ValueError, match="duration_s"):
        Fault.parse("unplug@3")


def test_the_virtual_servo_answers_the_sdk(tmp_path):
    """The SDK opens the pty link, pings, writes the return delay, reads the readings; the
    servo's reply to a packet with a bad checksum has the checksum error bit."""
    sdk = pytest.importorskip("dynamixel_sdk")
    import numpy as np

    from proprio_env.runtime.motion import ServoTrack
    from proprio_env.runtime.virtual_servo import VirtualServo

    t = np.linspace(0.0, 1.0, 11)
    track = ServoTrack(t, np.full(11, 60.0), np.full(11, 5.0), 20.0, 1.0)
    servo = VirtualServo(tmp_path / "ax12", track, servo_id=3, return_delay=0, ideal=True)
    servo.plug()
    th = threading.Thread(target=servo.serve, daemon=True)
    th.start()
    assert servo.serving.wait(30)  # after its garbage collection (long in a loaded process)
    try:
        port = sdk.PortHandler(str(tmp_path / "ax12"))
        assert port.openPort() and port.setBaudRate(1_000_000)
        packets = sdk.PacketHandler(1.0)
        assert packets.ping(port, 3)[:2] == (p.AX12_MODEL_NUMBER, sdk.COMM_SUCCESS)
        assert packets.write1ByteTxRx(port, 3, p.ADDR_RETURN_DELAY, 5) == (0, 0)
        assert servo.table[p.ADDR_RETURN_DELAY] == 5
        data, result, error = packets.readTxRx(port, 3, p.READINGS_ADDR, p.READINGS_LEN)
        assert (result, error) == (sdk.COMM_SUCCESS, 0)
        counts = data[0] | data[1] << 8
        # 60 deg through the default calibration (0 deg at 290.4 counts, 300/1023 deg/count)
        assert counts == round(290.4 + 60.0 * 1023 / 300)
        assert p.load_fraction(data[4] | data[5] << 8) == pytest.approx(5.0 / 20.0, abs=1e-3)
        port.writePort(p.instruction_packet(3, p.INST_PING)[:-1] + b"\x00")
        rx, result = packets.rxPacket(port)
        assert result == sdk.COMM_SUCCESS and rx[4] == p.ERR_CHECKSUM
    finally:
        servo.stop()
        th.join(5)
