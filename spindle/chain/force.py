"""Joint torque -> BRA and TRImed tendon forces, through the elbow model's moment arms.

On the prosthesis the servo's load reading gives one joint torque (N m, flexion positive);
the tendon organs need a force per muscle. The moment arms r(theta) = -dl_mtu/dtheta (m,
flexor positive) are MuJoCo's tendon Jacobian of ``models/elbow.xml`` tabulated every 0.5 deg
over the elbow range (``python scripts/fit_moment_arms.py``,
:mod:`proprio_env.body.moment_arm_fitting`), stored in ``models/moment_arm_fits.json`` beside the
length fits with the sha256 of the model, and interpolated linearly here (numpy only; a
table of 262 numbers per muscle, what a microcontroller would hold). Why not a smooth fit:
the paths wrap over the humerus cylinder and the moment arm has a kink where the wrap
engages, which a Chebyshev series of degree 40 still misses by 0.15 mm; and why not the
length fits' slope: those fits only bound the length, their slope is 5 % off OpenSim's
moment arm mid-range and 9 % at full extension.

The split (the documented rule): a load reading cannot tell co-contraction, so the torque is
carried by the one muscle that can produce it, none by the other --

    flexion torque (tau > 0):   F_BRA = tau / r_BRA,       F_TRImed = 0
    extension torque (tau < 0): F_TRImed = tau / r_TRImed,  F_BRA = 0

Both are >= 0 by construction (r_BRA > 0 > r_TRImed in the elbow's range; a fit whose moment
arm has the wrong sign or is shorter than :data:`MIN_MOMENT_ARM_M` is refused). Inputs: torque
and angle finite (ValueError otherwise); the angle inside the fits' range or, with
``clip=True``, clamped to it (the length model's rule).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spindle.chain.length_model import default_fits_path, file_sha256

__all__ = ["FORMAT", "MIN_MOMENT_ARM_M", "MOMENT_ARM_FITS_FILENAME", "MomentArmFits",
           "default_moment_arm_fits_path", "load_moment_arm_fits", "tendon_forces_N"]

FORMAT = "proprio-elbow/moment-arm-fits/1"
MOMENT_ARM_FITS_FILENAME = "moment_arm_fits.json"
REGENERATE = "python scripts/fit_moment_arms.py"

MIN_MOMENT_ARM_M = 1e-3
"""Shortest moment arm (m) a force is divided by: Arm26's are 12-23 mm (BRA) and 19-23 mm
(TRImed) over 0-130 deg."""


@dataclass(frozen=True)
class MomentArmFits:
    """Moment arms (m, flexor positive) per muscle, tabulated on a uniform angle grid.

    Attributes:
        muscles: names, in output order; table_m: one tuple per muscle, the moment arm at
        each of the n grid angles lo + k (hi - lo) / (n - 1); valid_range_rad: (lo, hi);
        model_sha256: of the ``elbow.xml`` they were made from; max_error_m: per muscle,
        the interpolation's largest error against MuJoCo between the grid angles.
    """

    muscles: tuple[str, ...]
    table_m: tuple[tuple[float, ...], ...]
    valid_range_rad: tuple[float, float]
    model_sha256: str
    max_error_m: tuple[float, ...]

    def moment_arms_m(self, angle_rad: np.ndarray | float, *, clip: bool = False
                      ) -> np.ndarray:
        """Moment arms (m) at ``angle_rad``: shape ``angle.shape + (n_muscles,)``."""
        angle = np.asarray(angle_rad, dtype=np.float64)
        lo, hi = self.valid_range_rad
        if not np.all(np.isfinite(angle)):
            raise ValueError(f"angle_rad={angle_rad!r} must be finite")
        if clip:
            angle = np.clip(angle, lo, hi)
        elif np.any((angle < lo) | (angle > hi)):
            raise ValueError(f"angle_rad={angle_rad!r} outside the fitted range "
                             f"[{lo}, {hi}] rad (clip=True clamps it)")
        grid = np.linspace(lo, hi, len(self.table_m[0]))
        return np.stack([np.interp(angle, grid, t) for t in self.table_m], axis=-1)


def default_moment_arm_fits_path() -> Path:
    """``moment_arm_fits.json`` beside the bundled length fits."""
    return default_fits_path().parent / MOMENT_ARM_FITS_FILENAME


def load_moment_arm_fits(path: str | Path | None = None, model: str | Path | None = None,
                         ) -> MomentArmFits:
    """The fits in ``path`` (default: the bundled file); with ``model`` (an ``elbow.xml``),
    ValueError if they were fitted to another file (regenerate with
    ``python scripts/fit_moment_arms.py``)."""
    path = Path(path) if path is not None else default_moment_arm_fits_path()
    try:
        doc = json.loads(path.read_text())
        if doc.get("format") != FORMAT:
            raise ValueError(f"format {doc.get('format')!r} is not {FORMAT!r}")
        names = tuple(doc["muscles"])
        fits = MomentArmFits(
            muscles=names,
            table_m=tuple(tuple(float(c) for c in doc["fits"][m]["table_m"]) for m in names),
            valid_range_rad=(float(doc["valid_range_rad"][0]), float(doc["valid_range_rad"][1])),
            model_sha256=str(doc["model_sha256"]),
            max_error_m=tuple(float(doc["fits"][m]["max_error_m"]) for m in names))
    except (OSError, ValueError, KeyError, TypeError, IndexError) as err:
        raise ValueError(f"{path}: not a moment-arm fits file ({err}); run {REGENERATE}"
                         ) from err
    if not all(np.all(np.isfinite(t)) and len(t) >= 2 for t in fits.table_m):
        raise ValueError(f"{path}: a table is non-finite or shorter than 2; run {REGENERATE}")
    if model is not None and file_sha256(model) != fits.model_sha256:
        raise ValueError(f"{path} was fitted to another model than {model}; run {REGENERATE}")
    return fits


def tendon_forces_N(torque_Nm: np.ndarray | float, angle_rad: np.ndarray | float,
                    fits: MomentArmFits, *, flexor: str = "BRA", extensor: str = "TRImed",
                    clip: bool = False) -> np.ndarray:
    """Tendon forces (N, >= 0) of the fits' muscles carrying joint torque ``torque_Nm`` (flexion
    positive) at ``angle_rad``, by the module's split. Shape ``broadcast.shape + (n_muscles,)``;
    muscles other than ``flexor`` and ``extensor`` get 0."""
    tau = np.asarray(torque_Nm, dtype=np.float64)
    if not np.all(np.isfinite(tau)):
        raise ValueError(f"torque_Nm={torque_Nm!r} must be finite")
    arms = fits.moment_arms_m(angle_rad, clip=clip)
    names = fits.muscles
    i_f, i_e = names.index(flexor), names.index(extensor)
    if not (np.all(arms[..., i_f] >= MIN_MOMENT_ARM_M)
            and np.all(arms[..., i_e] <= -MIN_MOMENT_ARM_M)):
        raise ValueError(f"moment arms {arms!r} (m): the flexor's must be >= "
                         f"{MIN_MOMENT_ARM_M} and the extensor's <= -{MIN_MOMENT_ARM_M}")
    tau, arms = np.broadcast_arrays(tau[..., None], arms)
    forces = np.zeros(tau.shape)
    flex = tau[..., i_f] > 0
    forces[..., i_f] = np.where(flex, tau[..., i_f] / arms[..., i_f], 0.0)
    forces[..., i_e] = np.where(~flex, tau[..., i_e] / arms[..., i_e], 0.0)
    return np.maximum(forces, 0.0)  # -0.0 of a zero torque becomes +0.0
