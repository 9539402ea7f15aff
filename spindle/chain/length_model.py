"""Reduced muscle-length model: elbow angle -> normalised fibre length by fitted polynomials.

The seed paper reduced OpenSim's fibre lengths to fitted equations so a microcontroller can
evaluate them. Here the fits are made from the MJCF elbow by ``python scripts/fit_lengths.py``
and stored in ``models/length_fits.json``: per muscle, Chebyshev coefficients over the valid
angle range, the maximum error against the exact MuJoCo length model, and the sha256 of the
``elbow.xml`` they were fitted to. This module only needs numpy (no MuJoCo): it is what runs
on the prosthesis.

Units: angles in rad, lengths in optimal fibre lengths (L0), velocities in L0/s.

Angles are checked: NaN/inf is always an error; an angle outside the valid range is an error
unless ``clip=True``, which clamps it to the range (the documented rule for, e.g., encoder
noise a fraction of a degree past the end stops).

Loading is checked too: every failure (missing, unreadable, not UTF-8, not JSON, a field of
the wrong type, non-finite numbers, fitted lengths leaving the spindle's valid range
:data:`spindle.core.LENGTH_RANGE_L0` anywhere in the angle range, a stale model hash) raises
:class:`LengthFitsError` naming the file and the regenerating command.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
from numpy.polynomial import chebyshev

from spindle.core import LENGTH_RANGE_L0

__all__ = [
    "DEFAULT_MODEL_FILE",
    "FITS_FILENAME",
    "FORMAT",
    "REGENERATE_COMMAND",
    "LengthFit",
    "LengthFits",
    "LengthFitsError",
    "check_length_range",
    "default_fits_path",
    "file_sha256",
    "length_fits_from_document",
    "load_length_fits",
]

FITS_FILENAME = "length_fits.json"
DEFAULT_MODEL_FILE = "elbow.xml"
"""The model a fits document that names none (no ``model`` field) was made from, beside it."""
FORMAT = "proprio-elbow/length-fits/1"
REGENERATE_COMMAND = "python scripts/fit_lengths.py"
_DATA_PACKAGE = "proprio_models"


class LengthFitsError(RuntimeError):
    """``length_fits.json`` is missing, malformed, or stale (fitted to another ``elbow.xml``)."""


def default_fits_path() -> Path:
    """Path of the bundled ``length_fits.json``.

    A source checkout (plain or editable install) uses the repository's ``models/``; a wheel
    install uses the installed data package ``proprio_models``.
    """
    checkout = Path(__file__).resolve().parents[2] / "models" / FITS_FILENAME
    if checkout.is_file():
        return checkout
    try:
        installed = resources.files(_DATA_PACKAGE)
    except ModuleNotFoundError as err:
        raise FileNotFoundError(
            f"cannot find the length fits: neither {checkout} nor an installed "
            f"'{_DATA_PACKAGE}' package exists; reinstall proprio-elbow"
        ) from err
    # Wheels install plain files, so the traversable is a real directory.
    return Path(str(installed)) / FITS_FILENAME


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes (the staleness check of the fits)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _check_angle_rad(
    angle_rad: np.ndarray | float, valid_range_rad: tuple[float, float], clip: bool
) -> np.ndarray:
    angle = np.asarray(angle_rad, dtype=float)
    if not np.all(np.isfinite(angle)):
        raise ValueError("elbow angle must be finite (got NaN or inf)")
    lo, hi = valid_range_rad
    if clip:
        return np.clip(angle, lo, hi)
    if np.any(angle < lo) or np.any(angle > hi):
        bad = angle[(angle < lo) | (angle > hi)].ravel()[0]
        raise ValueError(
            f"elbow angle {bad:.6g} rad ({math.degrees(bad):.4g} deg) is outside the fitted "
            f"range [{lo:.6g}, {hi:.6g}] rad; pass clip=True to clamp it to the range"
        )
    return angle


@dataclass(frozen=True)
class LengthFit:
    """Normalised fibre length of one muscle as a Chebyshev series in the elbow angle.

    Parameters
    ----------
    muscle : str
        OpenSim muscle name (``"BRA"``, ``"TRImed"``).
    coefficients : tuple of float
        Chebyshev coefficients (L0) in x = (2 angle - (lo + hi)) / (hi - lo), lowest first.
    valid_range_rad : (float, float)
        Angle range (rad) the fit was made on and may be evaluated in.
    max_error_L0 : float
        Largest deviation from the exact MuJoCo length model over the range, L0.
    """

    muscle: str
    coefficients: tuple[float, ...]
    valid_range_rad: tuple[float, float]
    max_error_L0: float

    @property
    def degree(self) -> int:
        """Polynomial degree."""
        return len(self.coefficients) - 1

    def _x(self, angle: np.ndarray) -> np.ndarray:
        lo, hi = self.valid_range_rad
        return (2.0 * angle - (lo + hi)) / (hi - lo)

    def length_L0(self, angle_rad: np.ndarray | float, *, clip: bool = False) -> np.ndarray:
        """Normalised fibre length (L0) at elbow angle(s) ``angle_rad`` (rad), same shape."""
        angle = _check_angle_rad(angle_rad, self.valid_range_rad, clip)
        return chebyshev.chebval(self._x(angle), self.coefficients)

    def derivative_L0_rad(
        self, angle_rad: np.ndarray | float, order: int = 1, *, clip: bool = False
    ) -> np.ndarray:
        """d^order L / d angle^order in L0/rad^order at ``angle_rad`` (rad), same shape."""
        angle = _check_angle_rad(angle_rad, self.valid_range_rad, clip)
        lo, hi = self.valid_range_rad
        # chebder works in x; dx/dangle = 2 / (hi - lo).
        coef = chebyshev.chebder(self.coefficients, m=order, scl=2.0 / (hi - lo))
        return chebyshev.chebval(self._x(angle), coef)


@dataclass(frozen=True)
class LengthFits:
    """The fits of all muscles, in a fixed muscle order (the last axis of every result).

    Parameters
    ----------
    fits : tuple of LengthFit
        One fit per muscle, in output order.
    valid_range_rad : (float, float)
        Elbow angle range (rad) shared by all fits.
    model_sha256 : str
        sha256 of the ``elbow.xml`` the fits were made from.
    """

    fits: tuple[LengthFit, ...]
    valid_range_rad: tuple[float, float]
    model_sha256: str

    @property
    def muscles(self) -> tuple[str, ...]:
        """Muscle names in output order."""
        return tuple(f.muscle for f in self.fits)

    def __getitem__(self, muscle: str) -> LengthFit:
        for fit in self.fits:
            if fit.muscle == muscle:
                return fit
        raise KeyError(f"no fit for muscle {muscle!r}; have {self.muscles}")

    def length_L0(self, angle_rad: np.ndarray | float, *, clip: bool = False) -> np.ndarray:
        """Normalised fibre lengths (L0), shape ``angle_rad.shape + (n_muscles,)``."""
        angle = _check_angle_rad(angle_rad, self.valid_range_rad, clip)
        columns = self._coefficient_columns
        if columns is None:
            return np.stack([f.length_L0(angle) for f in self.fits], axis=-1)
        # every muscle in one Clenshaw pass (fewer numpy calls: 151 vs 195 us for 64 angles,
        # shared 2-core machine, 2026-12-01); the leading zeros of a shorter series pass the
        # recurrence's values through exactly, so each muscle's lengths are
        # LengthFit.length_L0's, bit for bit
        return chebyshev.chebval(self.fits[0]._x(angle)[..., None], columns, tensor=False)

    @functools.cached_property
    def _coefficient_columns(self) -> np.ndarray | None:
        """(max degree + 1, n_muscles): each fit's coefficients, zero-padded to the longest;
        None if the fits' angle ranges differ (each then maps the angle to x itself) or a
        series is too short for the recurrence (chebval treats 1-2 coefficients apart)."""
        if (any(f.valid_range_rad != self.fits[0].valid_range_rad for f in self.fits)
                or min(len(f.coefficients) for f in self.fits) < 3):
            return None
        columns = np.zeros((max(len(f.coefficients) for f in self.fits), len(self.fits)))
        for j, f in enumerate(self.fits):
            columns[:len(f.coefficients), j] = f.coefficients
        return columns

    def velocity_L0_s(
        self,
        angle_rad: np.ndarray | float,
        angular_velocity_rad_s: np.ndarray | float,
        *,
        clip: bool = False,
    ) -> np.ndarray:
        """Fibre velocities (L0/s) = dL/dangle * angular velocity, shape ``(..., n_muscles)``.

        With ``clip=True`` an angle past the range is clamped and its slope taken at the end.
        """
        angle = _check_angle_rad(angle_rad, self.valid_range_rad, clip)
        omega = np.asarray(angular_velocity_rad_s, dtype=float)
        if not np.all(np.isfinite(omega)):
            raise ValueError("angular velocity must be finite (got NaN or inf)")
        slope = np.stack([f.derivative_L0_rad(angle) for f in self.fits], axis=-1)
        return slope * omega[..., None]


def _malformed(path: Path | str, why: str) -> LengthFitsError:
    return LengthFitsError(
        f"{path} is malformed ({why}); regenerate it with `{REGENERATE_COMMAND}`"
    )


def _number(value: object, what: str) -> float:
    """``value`` as a finite float if it is a JSON number (not a bool, string or list)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} is {value!r}, not a number")
    try:
        x = float(value)
    except OverflowError as err:  # a JSON integer beyond the float range
        raise ValueError(f"{what} {value!r} is too large for a float") from err
    if not math.isfinite(x):
        raise ValueError(f"{what} is {value!r}, not finite")
    return x


def _numbers(value: object, what: str) -> tuple[float, ...]:
    """``value`` as a tuple of finite floats if it is a JSON array of numbers."""
    if not isinstance(value, list):
        raise ValueError(f"{what} is {value!r}, not a list of numbers")
    return tuple(_number(v, f"{what}[{k}]") for k, v in enumerate(value))


def _length_extremes(fit: LengthFit) -> tuple[tuple[float, float], tuple[float, float]]:
    """(angle_rad, length_L0) of the shortest and the longest fibre over the fit's range.

    A polynomial's extremes on an interval lie at its ends or where its derivative vanishes;
    a dense grid backs up the roots (ill-conditioned at high degree).
    """
    coef = np.asarray(fit.coefficients, dtype=float)
    x = [np.array([-1.0, 1.0]), np.linspace(-1.0, 1.0, 1025)]
    if coef.size > 2:
        roots = chebyshev.chebroots(chebyshev.chebder(coef))
        real = roots.real[(np.abs(roots.imag) < 1e-9) & (np.abs(roots.real) <= 1.0)]
        x.append(real)
    xs = np.concatenate(x)
    length = chebyshev.chebval(xs, coef)
    lo, hi = fit.valid_range_rad
    angle = 0.5 * (lo + hi) + 0.5 * (hi - lo) * xs
    i_min, i_max = int(np.argmin(length)), int(np.argmax(length))
    return (float(angle[i_min]), float(length[i_min])), (float(angle[i_max]), float(length[i_max]))


def check_length_range(fits: LengthFits, source: str, remedy: str) -> None:
    """Raise :class:`LengthFitsError` if a fitted length leaves
    :data:`spindle.core.LENGTH_RANGE_L0` anywhere in the valid angle range.

    The message names ``source`` (the file or model), the muscle, the angle and the length,
    then ``remedy``. Outside that range the spindle model is undefined, so such fits would
    only fail later, mid-run (or, unchecked, give non-physiological rates).
    """
    low, high = LENGTH_RANGE_L0
    for fit in fits.fits:
        for angle, length in _length_extremes(fit):
            if not low <= length <= high:
                raise LengthFitsError(
                    f"{source}: the fitted {fit.muscle} fibre length is {length:.4g} L0 at "
                    f"{angle:.6g} rad ({math.degrees(angle):.4g} deg), outside the spindle's "
                    f"valid range [{low:g}, {high:g}] L0; {remedy}"
                )


def length_fits_from_document(
    doc: object, source: str | Path, *, remedy: str | None = None
) -> tuple[LengthFits, str]:
    """The fits in a parsed ``length_fits.json`` document and the model file name it records.

    ``source`` names the document in errors; ``remedy`` ends the message of a length out of
    range (default: regenerate the file). Every field must have its JSON type (numbers are
    numbers, not strings or booleans; ``coefficients`` a list of them), every number must be
    finite and every fitted length inside :data:`spindle.core.LENGTH_RANGE_L0`.

    Raises
    ------
    LengthFitsError
        Naming ``source``, the faulty field and the regenerating command.
    """
    if not isinstance(doc, Mapping):
        raise _malformed(source, "top level is not a JSON object")
    if doc.get("format") != FORMAT:
        raise _malformed(source, f"format is {doc.get('format')!r}, expected {FORMAT!r}")
    try:
        bounds = _numbers(doc["valid_range_rad"], "valid_range_rad")
        if len(bounds) != 2:
            raise ValueError(f"valid_range_rad has {len(bounds)} numbers, not 2")
        lo, hi = bounds
        sha = doc["model_sha256"]
        model_file = doc.get("model", DEFAULT_MODEL_FILE)
        if not isinstance(model_file, str):
            raise ValueError(f"model is {model_file!r}, not a file name")
        muscles = doc["muscles"]
        if not isinstance(muscles, Mapping):
            raise ValueError(f"muscles is {muscles!r}, not an object")
        fits = []
        for name, entry in muscles.items():
            if not isinstance(entry, Mapping):
                raise ValueError(f"muscles.{name} is {entry!r}, not an object")
            fits.append(LengthFit(
                muscle=str(name),
                coefficients=_numbers(entry["coefficients"], f"coefficients of {name}"),
                valid_range_rad=(lo, hi),
                max_error_L0=_number(entry["max_error_L0"], f"max_error_L0 of {name}"),
            ))
    except (KeyError, ValueError) as err:
        raise _malformed(source, f"{type(err).__name__}: {err}") from err
    if not lo < hi:
        raise _malformed(source, f"valid_range_rad [{lo}, {hi}] is not an increasing range")
    if not fits:
        raise _malformed(source, "no muscles")
    for fit in fits:
        if not fit.coefficients:
            raise _malformed(source, f"coefficients of {fit.muscle} are empty")
    if not (isinstance(sha, str) and len(sha) == 64
            and all(c in "0123456789abcdef" for c in sha.lower())):
        raise _malformed(source, "model_sha256 is not a sha256 hex digest")
    out = LengthFits(fits=tuple(fits), valid_range_rad=(lo, hi), model_sha256=sha)
    check_length_range(out, str(source),
                       remedy or f"regenerate it with `{REGENERATE_COMMAND}`")
    return out, model_file


def load_length_fits(
    path: str | Path | None = None,
    *,
    model_xml: str | Path | None = None,
    verify: bool = True,
) -> LengthFits:
    """Load and check ``length_fits.json``.

    Parameters
    ----------
    path : path, optional
        The json; default :func:`default_fits_path`.
    model_xml : path, optional
        The ``elbow.xml`` whose sha256 must match the one recorded in the json; default: the
        model file named in the json, next to it.
    verify : bool
        Check the hash (set False only on a device that carries the fits without the model).

    Raises
    ------
    LengthFitsError
        If the file is missing, unreadable (a directory, no permission, not UTF-8),
        malformed (see :func:`length_fits_from_document`; this includes fitted lengths
        outside :data:`spindle.core.LENGTH_RANGE_L0`) or stale; the message names the file
        and the regenerating command.
    """
    path = Path(path) if path is not None else default_fits_path()
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise LengthFitsError(
            f"{path} does not exist; generate it with `{REGENERATE_COMMAND}`"
        ) from err
    except (OSError, UnicodeDecodeError) as err:
        raise LengthFitsError(
            f"cannot read {path} as UTF-8 text ({type(err).__name__}: {err}); regenerate it "
            f"with `{REGENERATE_COMMAND}`"
        ) from err
    try:
        doc = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as err:
        raise _malformed(path, f"not valid JSON: {err}") from err
    fits, model_file = length_fits_from_document(doc, path)
    if verify:
        xml = Path(model_xml) if model_xml is not None else path.parent / model_file
        if not xml.is_file():
            raise LengthFitsError(
                f"cannot check {path} for staleness: model {xml} not found "
                "(pass model_xml=..., or verify=False on a device without the model)"
            )
        try:
            actual = file_sha256(xml)
        except OSError as err:
            raise LengthFitsError(
                f"cannot check {path} for staleness: cannot read model {xml} ({err})"
            ) from err
        if actual != fits.model_sha256:
            raise LengthFitsError(
                f"{path} is stale: it was fitted to an elbow.xml with sha256 "
                f"{fits.model_sha256[:12]}..., but {xml} has {actual[:12]}...; "
                f"regenerate it with `{REGENERATE_COMMAND}`"
            )
    return fits
