"""What the OpenSim oracle scripts (make_length_oracle, make_wrist_oracle) share: where their
models come from, and the CSV writing.

The tables are read back by tests and by ``proprio_env.experiments.ecrb``: '#' comment lines
(provenance), a header line, then rows at 10 significant digits.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

OPENSIM_MODELS = "https://github.com/opensim-org/opensim-models"


def osim_help(repo_path: str, default: Path) -> str:
    """``--osim`` help: the public source of the model and the default path."""
    return (f"the OpenSim model file, {repo_path} of {OPENSIM_MODELS} (download it, or clone "
            f"the repository); default: {default.resolve()}")


def missing_osim(path: Path, repo_path: str) -> str | None:
    """The error text when ``path`` is no file, naming where to get the model; else None."""
    if path.is_file():
        return None
    return (f"no such .osim file: {path}\nthe model is OpenSim's {repo_path} in the public "
            f"repository {OPENSIM_MODELS} (e.g. git clone --depth 1 {OPENSIM_MODELS}); "
            f"then pass --osim opensim-models/{repo_path}")


def write_table(path: Path, names: list[str], table: np.ndarray, header: str) -> None:
    """Write ``table`` (rows x len(names)) with ``header`` as '#' comment lines."""
    path.parent.mkdir(parents=True, exist_ok=True)
    comment = "".join(f"# {line}\n" for line in header.splitlines())
    with path.open("w", newline="\n") as f:
        f.write(comment)
        f.write(",".join(names) + "\n")
        for row in table:
            f.write(",".join(f"{v:.10g}" for v in row) + "\n")
