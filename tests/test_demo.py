"""The README's main job runs the whole chain end to end and writes finite signals."""

import csv
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "demo.py"


def test_demo_runs_the_chain_and_writes_a_figure_and_finite_signals(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path), "--duration",
                          "1.5"], capture_output=True, text=True, check=True, timeout=300,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    with (tmp_path / "demo_signals.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    # ~500 Hz encoder samples over 1.5 s
    assert 700 <= len(rows) <= 800
    values = np.array([[float(v) for v in row.values()] for row in rows])
    assert np.isfinite(values).all()
    col = {name: values[:, i] for i, name in enumerate(rows[0])}
    for muscle in ("BRA", "TRImed"):
        for stage in ("counts", "angle_deg", "length_L0", "gamma_static_pps",
                      "gamma_dynamic_pps", "ia_pps", "ii_pps"):
            name = stage if stage in ("counts", "angle_deg") else f"{muscle}_{stage}"
            assert name in col, name
        # a human spindle fires tens of pps, never hundreds (seed paper: G / 5)
        assert 5 < col[f"{muscle}_ia_pps"].max() < 150
        gs = col[f"{muscle}_gamma_static_pps"]
        assert gs.min() >= 20 and gs.max() <= 150
        assert set(np.unique(col[f"{muscle}_gamma_dynamic_pps"])) == {0.0, 100.0}
    # the force sense: the load word's torque follows MuJoCo's servo torque to its resolution
    # and noise (20 N m / 1023 counts, 3 counts: measured 0.06 N m RMS), Ib finite, >= 0
    for name in ("load_counts", "torque_Nm", "true_torque_Nm", "BRA_force_N", "TRImed_force_N",
                 "BRA_ib_pps", "TRImed_ib_pps"):
        assert name in col, name
    valid = (col["load_counts"] >= 0) & (col["load_counts"] <= 2047)
    assert np.sqrt(np.mean((col["torque_Nm"] - col["true_torque_Nm"])[valid] ** 2)) < 0.1
    assert col["BRA_ib_pps"].min() >= 0 and col["TRImed_ib_pps"].min() >= 0
    # the servo holds the forearm against gravity: a flexion torque on BRA, tens of pps
    assert np.median(col["torque_Nm"]) > 0.5 and 10 < np.median(col["BRA_ib_pps"]) < 100
    # the exact (MuJoCo lengths) and reduced (fits) chains agree to a fraction of a pps
    diffs = [float(x) for x in re.findall(r"exact vs reduced RMS Ia ([0-9.]+)", run.stdout)]
    assert len(diffs) == 2 and max(diffs) < 0.5
    # the stimulator stage: frequency-coded pulses of every channel, charge-balanced, as many
    # over the run as the integral of the channel's requested rate (each sample's rate held
    # to the next sample), within one pulse; computed here from the written signals
    with (tmp_path / "demo_pulses.csv").open() as fh:
        pulses = list(csv.DictReader(fh))
    assert pulses
    t = col["t_s"]
    dt = np.append(np.diff(t), t[-1] - t[-2])
    for label in {p["label"] for p in pulses} | {"BRA ia", "TRImed ib"}:
        muscle, afferent = label.split()
        requested = float(np.sum(col[f"{muscle}_{afferent}_pps"] * dt))
        delivered = sum(p["label"] == label for p in pulses)
        assert abs(delivered - requested) <= 1.0, (label, delivered, requested)
    for p in pulses:  # one amplitude for both phases: balanced when the phases are equal
        assert int(p["cathodic_us"]) == int(p["anodic_us"]) > 0 and int(p["amplitude_uA"]) > 0
