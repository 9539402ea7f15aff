"""Smoke run of scripts/train.py (:mod:`proprio_env.experiments.training`): PPO trains, the
three policies are evaluated on held-out targets, and the learning curve and numbers are
written."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("matplotlib")

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "train.py"

from proprio_env.experiments import training as train  # noqa: E402


def test_held_out_bands_are_never_trained_on():
    ranges = train.training_ranges()
    for lo, hi in ranges:
        for a, b in train.HELD_OUT_BANDS:
            assert hi <= a or lo >= b
    covered = sum(hi - lo for lo, hi in ranges) + sum(b - a for a, b in train.HELD_OUT_BANDS)
    assert covered == pytest.approx(train.TARGET_SPAN_DEG[1] - train.TARGET_SPAN_DEG[0])
    targets = train.held_out_targets(9)
    assert all(any(a < t < b for a, b in train.HELD_OUT_BANDS) for t in targets)


def test_smoke_run_trains_evaluates_and_plots(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    run = subprocess.run([sys.executable, str(SCRIPT), "--timesteps", "256", "--smoke",
                          "--out", str(tmp_path)], capture_output=True, text=True, env=env,
                         timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads((tmp_path / "eval.json").read_text())
    assert result["train"]["timesteps"] == 256
    for name in ("ppo", "zero", "random"):
        score = result[name]["mean_abs_err_deg"]
        assert np.isfinite(score)
        # the printed score is the written one
        assert f"{name} mean_abs_err_deg={score:.2f} " in run.stdout
    # Zero excitation: the arm hangs near straight under gravity (passive muscles only), so
    # the error is the held-out targets' mean (37.5, 62.5, 87.5 deg -> 62.5) minus a small
    # hanging angle.
    assert 62.5 - 15 < result["zero"]["mean_abs_err_deg"] < 62.5
    assert (tmp_path / "policy.zip").stat().st_size > 1000
    assert (tmp_path / "curve.png").stat().st_size > 5000
    with (tmp_path / "curve.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["timesteps"]) for r in rows] == [128, 256]  # one row per 128-step rollout
    assert all(float(r["elapsed_s"]) > 0 and np.isfinite(float(r["train_abs_err_deg"]))
               for r in rows)
