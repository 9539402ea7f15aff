"""Make the moment-arm table: MuJoCo's elbow moment arms per muscle every 0.5 deg.

The moment arm of a tendon about the elbow is r = -dl/dtheta, MuJoCo's tendon Jacobian
(``data.ten_J``). It is tabulated on a uniform grid over the joint range (:data:`GRID_DEG`)
and checked between the grid angles (where :mod:`spindle.chain.force` interpolates linearly,
without MuJoCo). The user-facing command is ``python scripts/fit_moment_arms.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from proprio_env.body.model import JOINT, MUSCLES, load_model, model_path
from proprio_env.body.muscle_length import elbow_range_rad
from spindle.chain.force import FORMAT, default_moment_arm_fits_path
from spindle.chain.length_model import file_sha256

__all__ = ["GRID_DEG", "TOLERANCE_M", "fit_moment_arm_document", "moment_arms_exact_m",
           "write_moment_arm_fits"]

GRID_DEG = 0.5
"""Table spacing (deg)."""
TOLERANCE_M = 5e-5
"""Largest interpolation error accepted between grid angles (m): 0.25 % of a 20 mm arm."""


def moment_arms_exact_m(angle_rad: np.ndarray, model=None) -> np.ndarray:
    """MuJoCo's moment arms (m, flexor positive), shape (len(angle), len(MUSCLES))."""
    import mujoco

    model = load_model() if model is None else model
    data = mujoco.MjData(model)
    joint = model.joint(JOINT)
    qadr, dadr = model.jnt_qposadr[joint.id], model.jnt_dofadr[joint.id]
    ids = [model.tendon(m).id for m in MUSCLES]
    out = np.empty((len(angle_rad), len(ids)))
    jac = np.zeros((model.ntendon, model.nv))
    for k, a in enumerate(np.asarray(angle_rad, dtype=float)):
        data.qpos[qadr] = a
        mujoco.mj_forward(model, data)
        if data.ten_J.size == model.ntendon * model.nv:
            jac[:] = data.ten_J.reshape(model.ntendon, model.nv)
        else:
            mujoco.mju_sparse2dense(jac, data.ten_J, data.ten_J_rownnz, data.ten_J_rowadr,
                                    data.ten_J_colind)
        out[k] = -jac[ids, dadr]
    return out


def fit_moment_arm_document(model_file: Path | None = None) -> dict:
    """The ``moment_arm_fits.json`` content for ``model_file`` (default: the bundled model)."""
    model_file = Path(model_file) if model_file is not None else model_path()
    model = load_model(model_file)
    lo, hi = elbow_range_rad(model)
    n = int(np.ceil(np.degrees(hi - lo) / GRID_DEG)) + 1
    grid = np.linspace(lo, hi, n)
    fine = np.linspace(lo, hi, 10 * (n - 1) + 1)  # 9 angles between grid angles
    table, exact = moment_arms_exact_m(grid, model), moment_arms_exact_m(fine, model)
    fits = {}
    for j, name in enumerate(MUSCLES):
        error = float(np.max(np.abs(np.interp(fine, grid, table[:, j]) - exact[:, j])))
        if error > TOLERANCE_M:
            raise ValueError(f"{name}: interpolation error {error:.3g} m > {TOLERANCE_M} m")
        fits[name] = {"table_m": [float(c) for c in table[:, j]], "max_error_m": error}
    return {"format": FORMAT, "generated_by": "python scripts/fit_moment_arms.py",
            "description": "elbow moment arms (m, flexor positive) = -d tendon length / d "
                           "angle from MuJoCo, on a uniform grid from lo to hi "
                           "(interpolate linearly)",
            "model": model_file.name, "model_sha256": file_sha256(model_file),
            "joint": JOINT, "valid_range_rad": [lo, hi], "muscles": list(MUSCLES),
            "fits": fits}


def write_moment_arm_fits(out: Path | None = None, model_file: Path | None = None) -> Path:
    """Fit and write the JSON (default: ``models/moment_arm_fits.json``); returns its path."""
    out = Path(out) if out is not None else default_moment_arm_fits_path()
    out.write_text(json.dumps(fit_moment_arm_document(model_file), indent=1) + "\n")
    return out
