"""A wheel (not only an editable install) must carry models/ and find it.

Builds the wheel from a copy of the tree, installs it with --no-deps into a fresh venv that
borrows numpy/mujoco from this interpreter (--system-site-packages; only the build backend
comes from PyPI), and runs the resolvers from outside the repository.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import venv
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
IGNORE = shutil.ignore_patterns(
    ".git", ".venv", "venv", "build", "dist", "out", "*.egg-info", "__pycache__", ".*_cache"
)

CHECK = textwrap.dedent(
    """
    import sys
    from pathlib import Path

    import mujoco
    import numpy as np

    import spindle.chain.length_model as lf
    from proprio_env.body.model import load_model, model_path
    from proprio_env.body.muscle_length import sweep

    prefix = Path(sys.prefix).resolve()
    for path in (Path(lf.__file__), model_path(), lf.default_fits_path()):
        assert prefix in path.resolve().parents, (path, prefix)
    fits = lf.load_length_fits()  # hash check against the installed elbow.xml
    exact = sweep(load_model(), np.radians([0.0, 65.0, 130.0]))
    assert np.max(np.abs(fits.length_L0(exact.angle_rad) - exact.fibre_length_L0)) < 1e-3

    # The envs, the C sources (compiled from the installed copy) and the validation data.
    import gymnasium as gym

    import proprio_env.envs
    import proprio_env.experiments.ecrb as ecrb
    from spindle.native import build

    assert prefix in Path(proprio_env.envs.__file__).resolve().parents
    assert prefix in build.SOURCE_DIR.resolve().parents and build.sources()
    env = gym.make("proprio_env/ElbowReach-v0", backend="c")
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(env.action_space.sample())
    assert np.isfinite(obs).all()
    assert prefix in Path(ecrb.__file__).resolve().parents
    assert ecrb.EcrbCurve.load().range_deg == (-70.0, 70.0)  # the bundled OpenSim table
    print("ok", model_path())
    """
)


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    done = subprocess.run(args, cwd=cwd, capture_output=True, text=True)
    assert done.returncode == 0, f"{args}\n{done.stdout}\n{done.stderr}"
    return done


@pytest.mark.slow
def test_wheel_install_finds_models(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(REPO, src, ignore=IGNORE)
    if not (src / "README.md").exists():
        # pyproject's readme must exist to build; the project README is not this test's subject.
        (src / "README.md").write_text("proprio-elbow\n")
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), str(src)], src)
    wheels = list(dist.glob("proprio_elbow-*.whl"))
    assert len(wheels) == 1

    env_dir = tmp_path / "venv"
    venv.create(env_dir, system_site_packages=True, with_pip=True)
    python = env_dir / ("Scripts" if sys.platform == "win32" else "bin") / "python"
    _run([str(python), "-m", "pip", "install", "--no-deps", "-q", str(wheels[0])], tmp_path)
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PROPRIO_C_CACHE": str(tmp_path / "ccache")}
    done = subprocess.run([str(python), "-c", CHECK], cwd=work, capture_output=True, text=True,
                          env=env)
    assert done.returncode == 0, f"{done.stdout}\n{done.stderr}"
    assert done.stdout.startswith("ok")
