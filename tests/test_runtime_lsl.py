"""The runtime's LSL outlets, received by inlets on this machine only.

liblsl reads its configuration once per process, so the LSL part runs in a child process
with ``LSLAPICFG`` pointing at the loopback-only ``lsl_api.cfg`` (IPv6 off, machine-scope
discovery on 127.0.0.1, 127.0.0.1 the only known peer, servers bound to 127.0.0.1)."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pylsl")
pytest.importorskip("dynamixel_sdk")

from proprio_env.runtime.sinks import LOOPBACK_LSL_CONFIG, write_loopback_lsl_config

ROOT = Path(__file__).resolve().parent.parent

CHILD = r'''
import json, os, sys, threading, time
import numpy as np
import pylsl
from proprio_env.runtime.cli import start_virtual_servo
from proprio_env.runtime.loop import Runtime
from proprio_env.runtime.sinks import CsvLog, LslSink
from proprio_env.runtime.sources import DynamixelSource
from spindle.chain import ChainConfig

out, duration, stall_s = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
inlet_buffer_s = int(sys.argv[4])
name = f"proprio-test-{os.getpid()}"


class IaPulses:
    """Test fixture: one event each time a Ia rate's running integral crosses an integer."""
    event_fields = ("t_s", "channel")

    def bind(self, labels, units):
        self.cols = np.array([i for i, lab in enumerate(labels) if lab.endswith("_ia_pps")])
        self.phase = np.zeros(self.cols.size)
        self.last = None

    def step(self, t_s, rates):
        dt = 0.0 if self.last is None else t_s - self.last
        self.last = t_s
        self.phase += rates[self.cols] * dt
        fire = np.flatnonzero(self.phase >= 1.0)
        self.phase[fire] -= 1.0
        ev = np.zeros(fire.size, dtype=[("t_s", float), ("channel", float)])
        ev["t_s"], ev["channel"] = t_s, fire
        return ev


child = start_virtual_servo(out + "/ax12", "scripted", [], extra=("--return-delay", "0"))
runtime = Runtime(DynamixelSource(out + "/ax12", latency_timer_ms=2.0),
                  backend="c", pulse_encoder=IaPulses(),
                  sinks=[LslSink(name, name, wait_for_consumers_s=20)],
                  log=CsvLog(out + "/log.csv"), duration_s=duration)
result = {}
thread = threading.Thread(target=lambda: result.update(runtime.run()))
thread.start()
inlets = []
for kind in ("rates", "pulses"):
    (info,) = pylsl.resolve_byprop("name", f"{name}-{kind}", 1, 20)
    inlet = pylsl.StreamInlet(info, max_buflen=inlet_buffer_s)
    inlet.open_stream(20)
    inlets.append(inlet)
meta = inlets[0].info()
ch = meta.desc().child("channels").child("channel")
labels, units = [], []
while not ch.empty():
    labels.append(ch.child_value("label"))
    units.append(ch.child_value("unit"))
    ch = ch.next_sibling()
got = {"rates": [], "rates_t": [], "pulses": []}
t_start = time.monotonic()
stalled = False
quiet_since = None
while True:
    if stall_s and not stalled and time.monotonic() - t_start > 0.5:
        time.sleep(stall_s)  # a consumer that stops pulling
        stalled = True
    n = 0
    for key, inlet in zip(("rates", "pulses"), inlets):
        chunk, stamps = inlet.pull_chunk(timeout=0.05)
        got[key] += chunk
        n += len(chunk)
        if key == "rates":
            got["rates_t"] += stamps
    if thread.is_alive() or n:
        quiet_since = None
    elif quiet_since is None:
        quiet_since = time.monotonic()
    elif time.monotonic() - quiet_since > 0.5:
        break
thread.join()
child.terminate()
child.wait(10)
json.dump({"summary": result, "labels": labels, "units": units,
           "srate": meta.nominal_srate(), "fmt": meta.channel_format(), **got},
          open(out + "/received.json", "w"))
'''


def run_child(tmp_path, duration_s, stall_s=0.0, inlet_buffer_s=360):
    cfg = write_loopback_lsl_config(tmp_path / "lsl_api.cfg")
    env = {**os.environ, "LSLAPICFG": str(cfg), "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path), str(duration_s),
                           str(stall_s), str(inlet_buffer_s)], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    received = json.loads((tmp_path / "received.json").read_text())
    with open(tmp_path / "log.csv", newline="") as f:
        log = list(csv.DictReader(f))
    return received, log


def published(log):
    return [r for r in log if r["status"] in ("accepted", "rejected")]


def test_the_config_keeps_lsl_on_the_loopback():
    text = LOOPBACK_LSL_CONFIG
    for line in ("IPv6 = disable", "ResolveScope = machine", "KnownPeers = {127.0.0.1}",
                 "MachineAddresses = {127.0.0.1}", "AddressesOverride = {127.0.0.1}",
                 "ListenAddress = 127.0.0.1"):
        assert line in text
    addresses = [w.strip("{},") for ln in text.splitlines() if "=" in ln and "{" in ln
                 for w in ln.split("=")[1].split()]
    assert set(addresses) == {"127.0.0.1"}


def test_an_inlet_receives_every_sample_and_pulse_in_order(tmp_path):
    received, log = run_child(tmp_path, 1.5)
    summary = received["summary"]
    assert received["labels"] == summary["channel_labels"]
    assert received["units"] == summary["units"]
    assert received["srate"] == 500.0 and received["fmt"] == 2  # cf_double64 in liblsl
    rows = published(log)
    assert len(rows) > 300
    rates = np.array(received["rates"])
    assert rates[:, 0].tolist() == [float(r["index"]) for r in rows]  # every one, in order
    for k, label in enumerate(summary["channel_labels"][1:], start=1):
        assert rates[:, k].tolist() == [float(r[label]) for r in rows], label  # bit for bit
    stamps = np.array(received["rates_t"])
    assert np.all(np.diff(stamps) > 0)
    with open(tmp_path / "log_events.csv", newline="") as f:
        events = list(csv.DictReader(f))
    assert len(events) == summary["counters"]["events"] > 10
    pulses = np.array(received["pulses"])
    assert pulses[:, 0].tolist() == [float(e["t_s"]) for e in events]
    assert pulses[:, 1].tolist() == [float(e["channel"]) for e in events]


@pytest.mark.slow
def test_a_stalled_consumer_loses_its_oldest_samples_but_not_the_log(tmp_path):
    """An inlet with a 1 s buffer that stops pulling for 2 s: liblsl drops its oldest
    samples, the runtime never waits for it, the log keeps every reading."""
    received, log = run_child(tmp_path, 4.0, stall_s=2.0, inlet_buffer_s=1)
    summary = received["summary"]
    assert len(log) == summary["counters"]["readings"]
    rows = published(log)
    got = np.array(received["rates"])[:, 0]
    assert np.all(np.diff(got) > 0)  # what arrives is in order
    assert got[-1] == float(rows[-1]["index"])  # and up to the last sample
    assert got.size < len(rows)  # the stall cost this consumer samples
