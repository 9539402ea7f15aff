"""CSV writing shared by the OpenSim oracle scripts (make_length_oracle, make_wrist_oracle).

The tables are read back by tests and by ``proprio_env.experiments.ecrb``: '#' comment lines
(provenance), a header line, then rows at 10 significant digits.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_table(path: Path, names: list[str], table: np.ndarray, header: str) -> None:
    """Write ``table`` (rows x len(names)) with ``header`` as '#' comment lines."""
    path.parent.mkdir(parents=True, exist_ok=True)
    comment = "".join(f"# {line}\n" for line in header.splitlines())
    with path.open("w", newline="\n") as f:
        f.write(comment)
        f.write(",".join(names) + "\n")
        for row in table:
            f.write(",".join(f"{v:.10g}" for v in row) + "\n")
