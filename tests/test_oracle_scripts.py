"""The OpenSim oracle scripts say where to get the model a user does not have."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("script", "repo_path"), [
    ("make_length_oracle.py", "Models/Arm26/arm26.osim"),
    ("make_wrist_oracle.py", "Models/WristModel/wrist.osim"),
])
def test_a_missing_model_names_its_public_source(tmp_path, script, repo_path):
    missing = tmp_path / "absent.osim"
    out = tmp_path / "never.csv"
    run = subprocess.run([sys.executable, str(ROOT / "scripts" / script), "--osim", str(missing),
                          "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert str(missing) in run.stderr
    assert "https://github.com/opensim-org/opensim-models" in run.stderr
    assert f"--osim opensim-models/{repo_path}" in run.stderr
    assert not out.exists()
    helped = subprocess.run([sys.executable, str(ROOT / "scripts" / script), "--help"],
                            capture_output=True, text=True, timeout=60)
    assert repo_path in " ".join(helped.stdout.split())
