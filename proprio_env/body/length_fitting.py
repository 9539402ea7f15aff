"""Make the reduced length model: fit angle -> normalised fibre length per muscle.

The exact model (:mod:`proprio_env.body.muscle_length`) is swept densely over the elbow range and
each muscle's curve is fitted by a Chebyshev series (``numpy.polynomial``). The degree is the
smallest whose error on held-out angles (every other sample, the fit made on the rest) is
within the tolerance; the final fit uses all samples. ``spindle.chain.length_model`` evaluates the
result without MuJoCo. The user-facing command is ``python scripts/fit_lengths.py``.

:func:`fits_for_model` is what the envs use: the committed fits for the bundled model (or a
byte-identical copy), otherwise a fit of the given model made on the spot (about half a
second) and cached in the process by the model file's sha256, so an edited ``elbow.xml``
never runs with another model's fits.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.polynomial import Chebyshev

from proprio_env.body.model import JOINT, model_path
from proprio_env.body.muscle_length import Sweep, elbow_range_rad, sweep
from spindle.chain.length_model import (
    FITS_FILENAME,
    FORMAT,
    REGENERATE_COMMAND,
    LengthFits,
    LengthFitsError,
    file_sha256,
    length_fits_from_document,
    load_length_fits,
)

if TYPE_CHECKING:
    import mujoco

__all__ = [
    "DegreeChoice",
    "choose_degree",
    "default_output",
    "fit_document",
    "fits_for_model",
    "sweep_for_fit",
    "write_fits",
]

DEFAULT_STEP_DEG = 0.05
DEFAULT_TOLERANCE_L0 = 5e-4  # half the 0.001 L0 target: margin for the final, all-sample fit
DEFAULT_MAX_DEGREE = 20
TARGET_L0 = 1e-3
"""Largest accepted max error of a fit against the exact model (L0)."""


@dataclass(frozen=True)
class DegreeChoice:
    """Outcome of the degree search for one muscle.

    Parameters
    ----------
    degree : int
        Chosen degree.
    heldout_max_error_L0 : np.ndarray
        Held-out max error (L0) for degrees 1..max_degree (index = degree - 1).
    """

    degree: int
    heldout_max_error_L0: np.ndarray


def choose_degree(
    angle_rad: np.ndarray,
    length_L0: np.ndarray,
    domain_rad: tuple[float, float],
    tolerance_L0: float = DEFAULT_TOLERANCE_L0,
    max_degree: int = DEFAULT_MAX_DEGREE,
) -> DegreeChoice:
    """Smallest degree whose held-out max error is within ``tolerance_L0``.

    Odd-indexed samples are held out (they sit between the fitted ones, where a polynomial
    that only interpolates its training points would show). If no degree qualifies, the one
    with the smallest held-out error is returned; the caller checks the final error.
    """
    train, test = slice(0, None, 2), slice(1, None, 2)
    errors = np.empty(max_degree)
    for deg in range(1, max_degree + 1):
        fit = Chebyshev.fit(angle_rad[train], length_L0[train], deg, domain=list(domain_rad))
        errors[deg - 1] = np.max(np.abs(fit(angle_rad[test]) - length_L0[test]))
    within = np.flatnonzero(errors <= tolerance_L0)
    degree = int(within[0] + 1) if within.size else int(np.argmin(errors) + 1)
    return DegreeChoice(degree=degree, heldout_max_error_L0=errors)


def sweep_for_fit(model: mujoco.MjModel, step_deg: float = DEFAULT_STEP_DEG) -> Sweep:
    """Exact model on a uniform grid over the whole joint range, both ends included."""
    lo, hi = elbow_range_rad(model)
    n = int(np.ceil(np.degrees(hi - lo) / step_deg)) + 1
    return sweep(model, np.linspace(lo, hi, n))


def fit_document(
    model: mujoco.MjModel,
    model_file: Path,
    step_deg: float = DEFAULT_STEP_DEG,
    tolerance_L0: float = DEFAULT_TOLERANCE_L0,
    max_degree: int = DEFAULT_MAX_DEGREE,
) -> tuple[dict, Sweep]:
    """The ``length_fits.json`` content for ``model`` (compiled from ``model_file``) and the
    exact sweep it was fitted to."""
    import mujoco

    exact = sweep_for_fit(model, step_deg)
    lo, hi = elbow_range_rad(model)
    muscles = {}
    for j, name in enumerate(exact.muscles):
        y = exact.fibre_length_L0[:, j]
        choice = choose_degree(exact.angle_rad, y, (lo, hi), tolerance_L0, max_degree)
        fit = Chebyshev.fit(exact.angle_rad, y, choice.degree, domain=[lo, hi])
        muscles[name] = {
            "degree": choice.degree,
            "coefficients": [float(c) for c in fit.coef],
            "max_error_L0": float(np.max(np.abs(fit(exact.angle_rad) - y))),
            "heldout_max_error_L0": float(choice.heldout_max_error_L0[choice.degree - 1]),
        }
    doc = {
        "format": FORMAT,
        "generated_by": REGENERATE_COMMAND,
        "description": (
            "Normalised fibre length (L0) of each muscle vs elbow angle (rad): rigid tendon, "
            "constant-width pennation, from MuJoCo tendon lengths. Chebyshev series: "
            "L = sum_k c_k T_k(x), x = (2*angle - (lo + hi)) / (hi - lo), [lo, hi] = "
            "valid_range_rad. max_error_L0 is against the exact model on the fit grid."
        ),
        "model": model_file.name,
        "model_sha256": file_sha256(model_file),
        "mujoco_version": mujoco.__version__,
        "joint": JOINT,
        "valid_range_rad": [lo, hi],
        "valid_range_deg": [float(np.degrees(lo)), float(np.degrees(hi))],
        "grid_step_deg": step_deg,
        "tolerance_L0": tolerance_L0,
        "muscles": muscles,
    }
    return doc, exact


def write_fits(doc: dict, path: Path) -> None:
    """Write the document as stable, diff-friendly JSON (LF line ends, trailing newline)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8", newline="\n")


def default_output(model_file: Path | None = None) -> Path:
    """Where the fits go: next to the model they were made from."""
    return (model_file or model_path()).parent / FITS_FILENAME


_FITTED: dict[str, LengthFits] = {}
_FITTED_LOCK = threading.Lock()


def fits_for_model(model_file: str | Path | None = None,
                   model: mujoco.MjModel | None = None) -> LengthFits:
    """The length fits of the MJCF ``model_file`` (default: the bundled ``elbow.xml``).

    A file with the sha256 recorded in the committed ``length_fits.json`` gets those fits
    (loaded without fitting).
    Any other model is swept and fitted here with the defaults of ``scripts/fit_lengths.py``
    (about 0.6 s), once per process: the result is cached by the file's sha256. ``model`` is
    the already compiled ``model_file`` (compiled here if ``None``).

    Raises
    ------
    LengthFitsError
        If a fit misses :data:`TARGET_L0` or a fitted length leaves the spindle's valid
        range (:func:`spindle.chain.length_model.check_length_range`); the message names the model,
        and the muscle, angle and length or the command that fits it with other settings.
    """
    path = Path(model_file) if model_file is not None else model_path()
    try:
        sha = file_sha256(path)
    except OSError as err:
        raise LengthFitsError(f"cannot read the model {path} to fit its lengths: {err}") from err
    with _FITTED_LOCK:
        cached = _FITTED.get(sha)
    if cached is not None:
        return cached
    # Unverified: the question is only whether the committed fits were made for this file.
    committed = load_length_fits(verify=False)
    if committed.model_sha256 == sha:
        fits = committed
    else:
        if model is None:
            from proprio_env.body.model import load_model

            model = load_model(path)
        command = f"python scripts/fit_lengths.py --model {path} --fits <out.json>"
        doc, _ = fit_document(model, path)
        if doc["model_sha256"] != sha:
            raise LengthFitsError(f"{path} changed while its lengths were being fitted")
        for name, entry in doc["muscles"].items():
            if entry["max_error_L0"] > TARGET_L0:
                raise LengthFitsError(
                    f"model {path}: the best fit of {name} (degree {entry['degree']}) is "
                    f"{entry['max_error_L0']:.3g} L0 from the exact lengths, above the "
                    f"{TARGET_L0:g} L0 target; try `{command} --max-degree 30` and pass the "
                    "json as ChainConfig(fits_path=...)")
        fits, _ = length_fits_from_document(
            doc, f"model {path}",
            remedy="the spindle model is undefined there; change the model's muscle path "
                   "or joint range")
    with _FITTED_LOCK:
        return _FITTED.setdefault(sha, fits)
