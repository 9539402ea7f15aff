"""The runtime against the virtual AX-12 on a pty, through dynamixel_sdk: its outputs are
the offline chain's on the readings it logged, bit for bit; the log misses none of the
readings the servo sent; each fault is survived and counted."""

from __future__ import annotations

import csv
import os

import numpy as np
import pytest

pytest.importorskip("dynamixel_sdk")

from proprio_env.runtime import protocol as p
from proprio_env.runtime.cli import start_virtual_servo
from proprio_env.runtime.loop import Runtime
from proprio_env.runtime.sinks import CallbackSink, CsvLog
from proprio_env.runtime.sources import DynamixelSource
from spindle.chain import MUSCLES, ChainConfig, run_chain

READ = ("accepted", "rejected", "before_start")


def run_against_servo(tmp_path, duration_s, faults=(), backend="auto", seed=3):
    link = str(tmp_path / "ax12")
    record = tmp_path / "servo.csv"
    child = start_virtual_servo(link, "scripted", list(faults),
                                extra=("--return-delay", "0", "--seed", str(seed),
                                       "--record", str(record)))
    try:
        # 2 ms latency timer: a 6.2 ms reply timeout, generous for a loaded machine
        source = DynamixelSource(link, latency_timer_ms=2.0, reconnect_s=0.05)
        runtime = Runtime(source, backend=backend,
                          log=CsvLog(tmp_path / "log.csv"), duration_s=duration_s)
        summary = runtime.run()
    finally:
        child.terminate()
        child.wait(10)
    with open(tmp_path / "log.csv", newline="") as f:
        log = list(csv.DictReader(f))
    with open(record, newline="") as f:
        servo = list(csv.DictReader(f))
    return runtime, summary, log, servo


def assert_equals_offline_chain(log, backend):
    read = [r for r in log if r["status"] in READ]
    t = np.array([float(r["t_s"]) for r in read])
    counts = np.array([float(r["counts"]) for r in read])
    load = np.array([float(r["load_raw"]) for r in read])
    trace = run_chain(t, counts=counts, load=load, config=ChainConfig(backend=backend))
    live = [i for i, r in enumerate(read) if r["status"] != "before_start"]
    assert live, "the chain never started"
    logged_torque = np.array([float(read[i]["torque_Nm"]) for i in live])
    assert np.array_equal(logged_torque, trace.torque_Nm[live])
    assert np.ptp(logged_torque) > 0.05  # the load moved, and the tendon organs with it
    for name in ("ia_pps", "ii_pps", "gamma_static_pps", "gamma_dynamic_pps", "length_L0",
                 "force_N", "ib_pps"):
        for k, m in enumerate(MUSCLES):
            logged = np.array([float(read[i][f"{m}_{name}"]) for i in live])
            assert np.array_equal(logged, getattr(trace, name)[live, k]), (name, m)
    accepted = np.array([read[i]["accepted"] == "1" for i in live])
    assert np.array_equal(accepted, trace.accepted[live])
    assert np.array_equal([read[i]["status"] == "accepted" for i in live], accepted)


def assert_no_reading_missing(log, servo):
    """Walk the servo's record of every READ it received beside the log: each reply with a
    reading is in the log, in order, with its words; a dropped reply is a timeout, a bad
    checksum a corrupt row; the read the servo was unplugged on failed. A reply later than the
    timeout (the machine is loaded) is a timeout row too, and its late reply is dropped as
    stale by the next read (``stale_replies``), never logged as that read's. Returns how
    often each (log status, servo fault) pair came."""
    from collections import Counter

    pairs, j = Counter(), 0
    for row in log:
        status = row["status"]
        if status == "unplugged" and (j == len(servo) or servo[j]["fault"] != "unplug"):
            continue  # the port was closed: no request reached the servo
        sent = servo[j]
        j += 1
        pairs[status, sent["fault"]] += 1
        if sent["fault"] == "unplug":
            assert status in ("unplugged", "timeout", "corrupt")
        elif status in READ:
            assert sent["fault"] in ("", "range")
            assert (int(row["counts"]), int(row["load_raw"])) == (
                int(sent["position"]), int(sent["load"]))
        elif status == "timeout":
            assert sent["fault"] in ("drop", "")
        else:
            assert (status, sent["fault"]) == ("corrupt", "checksum")
    assert j == len(servo)
    return pairs


@pytest.mark.parametrize("backend", ["c", pytest.param("numpy", marks=pytest.mark.slow)])
def test_outputs_equal_the_offline_chain_on_the_logged_readings(tmp_path, backend):
    runtime, summary, log, servo = run_against_servo(tmp_path, 2.0, backend=backend)
    assert runtime.backend == backend
    c = summary["counters"]
    # 1000 ticks in 2 s, each read or skipped.
    # How many are skipped is timing (scripts/bench_runtime.py): on this loaded 2-core
    # machine without real-time priority C read 740-1000, numpy 817 of 1250 in 2.5 s
    assert c["readings"] + c["skipped_ticks"] == 1000
    assert c["readings"] > 300
    assert c["readings"] == len(log) == c["accepted"] + c["rejected"] + c["before_start"] + (
        c["timeout"] + c["corrupt"] + c["unplugged"])
    assert [int(r["index"]) for r in log] == sorted(int(r["index"]) for r in log)
    assert_no_reading_missing(log, servo)
    assert_equals_offline_chain(log, backend)
    # the encoder model's glitches (1 in 1000) reach the log as rejected readings
    rejected = [r for r in log if r["status"] == "rejected"]
    assert all(int(r["counts"]) > 1023 for r in rejected)
    assert c["rejected"] == summary["chain_counters"]["invalid_reading"]
    loads = np.array([p.load_fraction(int(r["load_raw"])) for r in log if r["status"] in READ])
    assert np.all(np.abs(loads) <= 1) and np.ptp(loads) > 0.05  # the load follows the motion


def test_every_fault_is_survived_counted_and_logged(tmp_path):
    faults = ("checksum@100x3", "drop@200", "range@300x2", "unplug@400:0.3", "drop@600x2")
    _, summary, log, servo = run_against_servo(tmp_path, 3.0, faults)
    c, chain = summary["counters"], summary["chain_counters"]
    pairs = assert_no_reading_missing(log, servo)
    assert c["corrupt"] == pairs["corrupt", "checksum"] == 3  # corrupt replies, not readings
    assert pairs["timeout", "drop"] == 3  # each dropped reply timed out
    # (a reply later than the 6.2 ms timeout on this loaded machine is a timeout too)
    assert c["timeout"] == 3 + pairs["timeout", ""] + pairs["timeout", "unplug"]
    # the read the servo was unplugged on failed, and so did every read until it was back
    assert sum(pairs[s, "unplug"] for s in ("unplugged", "timeout", "corrupt")) == 1
    assert c["unplugged"] >= 1 and c["reconnects"] == 1
    # the two out-of-range positions reach the chain, which rejects them by its rule
    out_of_range = [r for r in log if r["counts"] == str(0x0500)]
    assert len(out_of_range) == 2 and all(r["status"] == "rejected" for r in out_of_range)
    assert chain["invalid_reading"] == c["rejected"]
    # 0.3 s unplugged > max_bridge_s (50 ms): the chain restarted at rest; the 3-sample
    # checksum run (6 ms) and the drops were bridged or are plain gaps
    assert chain["restarts"] >= 1 and chain["gaps"] >= 1
    assert int(servo[-1]["read"]) > 650  # every fault came
    after = [r for r in log[-100:] if r["status"] == "accepted"]
    assert len(after) > 75  # running normally again at the end
    assert_equals_offline_chain(log, "c")


def test_a_servo_that_is_not_there_is_a_clear_error(tmp_path):
    with pytest.raises(OSError, match="ax12"):
        DynamixelSource(str(tmp_path / "ax12")).open()
    with pytest.raises(ValueError, match="baud_rate=12345"):
        DynamixelSource("/dev/null", baud_rate=12345)
    with pytest.raises(ValueError, match="servo_id=254"):
        DynamixelSource("/dev/null", servo_id=254)


def test_a_replayed_log_gives_the_same_outputs(tmp_path):
    """A replay of the log feeds the same readings with their times: the same outputs."""
    from proprio_env.runtime.sources import ReplaySource

    _, _, log, _ = run_against_servo(tmp_path, 1.0, ("drop@100",))
    out = tmp_path / "replay"
    out.mkdir()
    runtime = Runtime(ReplaySource(tmp_path / "log.csv"), rate_hz=5000,
                      backend="c", log=CsvLog(out / "log.csv"))
    runtime.run()
    with open(out / "log.csv", newline="") as f:
        again = list(csv.DictReader(f))
    assert [r["status"] for r in again] == [r["status"] for r in log]
    for name in ("t_s", "counts", "BRA_ia_pps", "TRImed_ii_pps", "BRA_gamma_dynamic_pps"):
        assert [r[name] for r in again] == [r[name] for r in log], name


def test_sigterm_flushes_and_closes_the_log(tmp_path):
    import signal
    import threading

    from proprio_env.runtime.sources import SimulatedElbowSource

    published = []

    def terminate_after_150(row):
        # the signal once 150 samples are out (a fixed delay may see few on a busy machine)
        published.append(row)
        if len(published) == 150:
            threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGTERM)).start()

    runtime = Runtime(SimulatedElbowSource("scripted"), backend="c",
                      log=CsvLog(tmp_path / "log.csv", flush_every=10**9),
                      sinks=[CallbackSink(terminate_after_150)])
    summary = runtime.run()  # returns on SIGTERM instead of running forever
    with open(tmp_path / "log.csv", newline="") as f:
        log = list(csv.DictReader(f))
    assert len(log) == summary["counters"]["readings"] > 100
    assert (tmp_path / "log_summary.json").is_file()


@pytest.mark.slow
def test_the_command_line_runs_a_simulated_elbow(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.run([sys.executable, "-m", "proprio_env.runtime.cli", "--source",
                           "simulated", "--track", "scripted", "--duration", "0.5", "--no-lsl",
                           "--quiet", "--backend", "c", "--log", str(tmp_path / "run.csv")],
                          env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((tmp_path / "run_summary.json").read_text())
    assert summary["backend"] == "c" and summary["counters"]["readings"] > 100
    assert "deadline misses" in proc.stderr


class Doubler:
    """A stage of the test: twice the BRA Ia rate, and the servo load."""

    channel_labels = ("twice_BRA_ia", "load")
    units = ("pps", "fraction")

    def step(self, t_s, sample):
        return np.array([2 * sample.chain.ia_pps[0], sample.reading.load_fraction])


def test_stages_and_the_callback_see_every_published_sample(tmp_path):
    from proprio_env.runtime.sinks import CallbackSink
    from proprio_env.runtime.sources import SimulatedElbowSource
    from proprio_env.runtime.stages import LoadStage, SpindleStage

    rows = []
    runtime = Runtime(SimulatedElbowSource("scripted"), backend="c",
                      stages=[SpindleStage(), Doubler(), LoadStage()],
                      sinks=[CallbackSink(rows.append)], log=CsvLog(tmp_path / "log.csv"),
                      duration_s=0.5)
    summary = runtime.run()
    assert summary["channel_labels"][-3:] == ["twice_BRA_ia", "load", "servo_load"]
    with open(tmp_path / "log.csv", newline="") as f:
        log = [r for r in csv.DictReader(f) if r["status"] in ("accepted", "rejected")]
    assert [r.index for r in rows] == [int(r["index"]) for r in log] and len(rows) > 50
    for row, logged in zip(rows, log, strict=True):
        assert row.values[0] == row.index
        assert row.values[-3] == 2 * float(logged["BRA_ia_pps"])
        assert row.values[-2] == row.values[-1] == float(logged["load_fraction"])


def test_bad_stages_and_settings_are_refused_before_anything_runs():
    from proprio_env.runtime.sources import SimulatedElbowSource
    from proprio_env.runtime.stages import SpindleStage

    source = SimulatedElbowSource("scripted")
    with pytest.raises(TypeError, match="is not a stage"):
        Runtime(source, stages=[object()])
    with pytest.raises(ValueError, match="channel labels repeat"):
        Runtime(source, stages=[SpindleStage(), SpindleStage()])
    with pytest.raises(ValueError, match="rate_hz=0"):
        Runtime(source, rate_hz=0)
    with pytest.raises(ValueError, match="rt_priority=100"):
        Runtime(source, rt_priority=100)

    class NoTime:
        event_fields = ("channel",)

        def step(self, t_s, rates):
            return np.zeros(0)

    with pytest.raises(ValueError, match="t_s among them"):
        Runtime(source, pulse_encoder=NoTime())
    with pytest.raises(ValueError, match="backend='gpu'"):
        Runtime(source, backend="gpu")


def test_a_stage_that_returns_nan_stops_with_its_name_and_the_log_is_closed(tmp_path):
    from proprio_env.runtime.sources import SimulatedElbowSource

    class Broken:
        channel_labels, units = ("x",), ("1",)

        def step(self, t_s, sample):
            return np.array([np.nan])

    runtime = Runtime(SimulatedElbowSource("scripted"), backend="c", stages=[Broken()],
                      log=CsvLog(tmp_path / "log.csv"), duration_s=1.0)
    with pytest.raises(ValueError, match=r"Broken.*expected 1 finite values"):
        runtime.run()
    assert (tmp_path / "log_summary.json").is_file()
    with open(tmp_path / "log.csv", newline="") as f:
        log = list(csv.DictReader(f))
    assert log[-1]["status"] == "error" and log[-1]["counts"] != ""  # the reading is kept


def test_the_stimulation_encoder_pulses_equal_the_offline_stimulator_on_the_published_rates():
    """The runtime's default pulse encoder (the stimulator stage) against the stimulator run
    offline (spindle.stimulation, the same backend) on the rates the runtime published: each
    sample's rates held until the next, the same events bit for bit."""
    from proprio_env.runtime.sources import SimulatedElbowSource
    from proprio_env.runtime.stages import StimulationEncoder
    from spindle.stimulation import make_stimulator

    rows = []
    encoder = StimulationEncoder(backend="c")
    runtime = Runtime(SimulatedElbowSource("scripted"), backend="c", pulse_encoder=encoder,
                      sinks=[CallbackSink(rows.append)], duration_s=1.5)
    runtime.run()
    published = [r for r in rows if r.values is not None]
    labels = runtime.layout.channel_labels
    columns = [labels.index(f"{c.muscle}_{c.afferent}_pps")
               for c in encoder.config.channels.channels]
    t = np.array([r.t_s for r in published])
    rates = np.array([r.values for r in published])[:, columns]
    assert np.all(np.diff(t) > 0) and encoder.restarts == 0
    offline = make_stimulator(encoder.config, backend="c", t0_s=float(t[0]))
    want = offline.run(rates[:-1], np.diff(t))
    got = np.concatenate([r.events for r in published])
    assert want.size > 20  # measured 51 pulses over 1.5 s of the scripted motion
    np.testing.assert_array_equal(got["t_s"], want["time_s"])
    for name in ("channel", "amplitude_uA", "cathodic_us", "gap_us", "anodic_us"):
        np.testing.assert_array_equal(got[name], want[name])
