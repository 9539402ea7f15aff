"""Pulse events: one row per delivered biphasic pulse, saved as CSV or npz.

Each pulse is symmetric, cathodic first: ``amplitude_uA`` for ``cathodic_us``, no current for
``gap_us``, then ``amplitude_uA`` of the opposite sign for ``anodic_us`` (= ``cathodic_us``).
Both phases' charges are the integer ``amplitude_uA * width_us`` (pC), equal exactly.
:data:`PULSE_DTYPE` has the layout of ``ps_pulse`` in ``proprio.h`` (aligned), so a C event
buffer is read without conversion.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

PULSE_DTYPE = np.dtype([("time_s", "<f8"), ("channel", "<i4"), ("amplitude_uA", "<i4"),
                        ("cathodic_us", "<i4"), ("gap_us", "<i4"), ("anodic_us", "<i4")],
                       align=True)
"""One pulse: start time (s), channel index, amplitude (µA), phase widths and gap (µs)."""


def empty_events(n: int = 0) -> np.ndarray:
    return np.zeros(n, dtype=PULSE_DTYPE)


def charges_pC(events: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cathodic, anodic) charge of each pulse in pC, as int64 (exact)."""
    amp = events["amplitude_uA"].astype(np.int64)
    return amp * events["cathodic_us"], amp * events["anodic_us"]


def save_npz(path: str | Path, events: np.ndarray, labels: tuple[str, ...] = ()) -> None:
    """``events`` (and the channel labels, index order) into a compressed ``.npz``."""
    np.savez_compressed(path, events=np.asarray(events, dtype=PULSE_DTYPE),
                        labels=np.array(labels, dtype=str))


def load_npz(path: str | Path) -> tuple[np.ndarray, tuple[str, ...]]:
    with np.load(path) as data:
        return data["events"].astype(PULSE_DTYPE), tuple(str(s) for s in data["labels"])


def save_csv(path: str | Path, events: np.ndarray, labels: tuple[str, ...] = ()) -> None:
    """One header line then one pulse per line; times to the nanosecond (``%.9f``); a
    ``label`` column when ``labels`` is given."""
    names = list(PULSE_DTYPE.names)
    with Path(path).open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(names + (["label"] if labels else []))
        for row in np.asarray(events, dtype=PULSE_DTYPE):
            values = [f"{row['time_s']:.9f}"] + [str(int(row[n])) for n in names[1:]]
            writer.writerow(values + ([labels[row["channel"]]] if labels else []))


def load_csv(path: str | Path) -> np.ndarray:
    with Path(path).open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    out = empty_events(len(rows))
    for name in PULSE_DTYPE.names:
        out[name] = [float(r[name]) if name == "time_s" else int(r[name]) for r in rows]
    return out
