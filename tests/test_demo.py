"""The README's main job runs end to end and writes finite signals."""

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "demo.py"


def test_demo_writes_a_figure_and_finite_signals(tmp_path):
    run = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path), "--duration",
                          "1.5"], capture_output=True, text=True, check=True, timeout=120)
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    with (tmp_path / "demo_signals.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1500
    values = np.array([[float(v) for v in row.values()] for row in rows])
    assert np.isfinite(values).all()
    ia = np.array([float(r["BRA_ia_pps"]) for r in rows])
    # a human spindle at 70 pps drive fires tens of pps, never hundreds (seed paper: G / 5)
    assert 5 < ia.max() < 150
    assert "BRA" in run.stdout
