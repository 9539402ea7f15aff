"""No optional extra may replace the MuJoCo the core resolves to.

Each extra of pyproject.toml is resolved by pip (``install --dry-run --report``, nothing is
installed) in a throwaway venv, beside the core alone; MuJoCo's version must be the same in
both. myo-sim, for one, declares ``mujoco<4`` and pulled MuJoCo 3.17 over 4.0 when it sat in
the ``myo`` extra. Needs the package index (network), so slow: ``.ci/run`` runs it with
``python -m pytest -m slow tests/test_extras.py``.
"""
from __future__ import annotations

import json
import re
import subprocess
import tomllib
import venv
from pathlib import Path

import pytest

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
_REQ_NAME = re.compile(r"^\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*(\[([^\]]*)\])?(.*)$")


def _project() -> dict:
    return tomllib.loads(PYPROJECT.read_text())["project"]


def requirements(extra: str | None) -> list[str]:
    """The core's requirements, plus an extra's with the project's own extras expanded."""
    project = _project()
    extras = project["optional-dependencies"]
    out = list(project["dependencies"])
    todo, seen = ([extra] if extra else []), set()
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for req in extras[name]:
            m = _REQ_NAME.match(req)
            if m and m.group(1) == project["name"]:
                todo += [e.strip() for e in m.group(3).split(",")]
            else:
                out.append(req)
    return out


def test_requirements_expand_the_project_s_own_extras():
    dev = requirements("dev")
    assert "ruff>=0.5" in dev and "unicorn>=2.1" in dev and "pytest>=8" in dev
    assert not any(r.startswith(_project()["name"]) for r in dev)


@pytest.fixture(scope="module")
def pip(tmp_path_factory):
    env_dir = tmp_path_factory.mktemp("extras-venv")
    venv.create(env_dir, with_pip=True)           # empty: sees nothing installed here
    return [str(env_dir / "bin" / "python"), "-m", "pip"]


def resolved_versions(pip: list[str], reqs: list[str], report: Path) -> dict[str, str]:
    """{normalised name: version} pip would install into the empty venv for ``reqs``."""
    run = subprocess.run([*pip, "install", "--dry-run", "--quiet", "--report", str(report),
                          *reqs], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f"pip could not resolve {reqs}:\n{run.stderr[-3000:]}"
    items = json.loads(report.read_text())["install"]
    return {re.sub(r"[-_.]+", "-", i["metadata"]["name"]).lower(): i["metadata"]["version"]
            for i in items}


@pytest.fixture(scope="module")
def core(pip, tmp_path_factory):
    return resolved_versions(pip, requirements(None), tmp_path_factory.mktemp("core") / "r.json")


@pytest.mark.slow
@pytest.mark.parametrize("extra", sorted(_project()["optional-dependencies"]))
def test_no_extra_replaces_the_core_mujoco(pip, core, tmp_path, extra):
    with_extra = resolved_versions(pip, requirements(extra), tmp_path / f"{extra}.json")
    assert with_extra["mujoco"] == core["mujoco"], (
        f"the {extra!r} extra resolves MuJoCo {with_extra['mujoco']} instead of the core's "
        f"{core['mujoco']}: one of {requirements(extra)} caps it")
