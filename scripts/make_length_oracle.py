"""Regenerate the OpenSim length oracle of BRA and TRImed, ``tests/data/arm26_elbow_oracle.csv``.

Needs the optional ``opensim`` package (``pip install -e .[opensim]``); nothing else in the
project does. Run from anywhere::

    git clone --depth 1 https://github.com/opensim-org/opensim-models
    python scripts/make_length_oracle.py --osim opensim-models/Models/Arm26/arm26.osim
    python scripts/make_length_oracle.py --osim path/to/arm26.osim --out other.csv

The model is OpenSim's ``Models/Arm26/arm26.osim`` of
https://github.com/opensim-org/opensim-models;
without ``--osim`` the maintainers' copy in ../shared/reference/opensim/ is used.

For every elbow angle 0..130 deg (1 deg steps, shoulder elevation 0) it writes, per muscle:

- ``{m}_mtu_length_m`` - musculotendon (path) length, m
- ``{m}_moment_arm_m`` - moment arm about ``r_elbow_flex``, m (flexor positive)
- ``{m}_norm_fiber_length`` - fibre length / optimal fibre length at passive equilibrium
  (elastic tendon, activation 0.01, ``Model.equilibrateMuscles``)
- ``{m}_pennation_rad`` - pennation angle at passive equilibrium, rad
- ``{m}_rigid_norm_fiber_length`` - rigid tendon (tendon = slack length): OpenSim's own
  ``MuscleFixedWidthPennationModel.calcFiberLength`` of the muscle, / optimal fibre length
  (Thelen2003Muscle does not implement ``ignore_tendon_compliance``)
- ``{m}_wrap_engaged`` - 1 where the path wraps over the TRI cylinder

The .osim file is read, never copied: it stays in ../shared/reference/opensim/.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from oracle_csv import missing_osim, osim_help, write_table

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OSIM = REPO_ROOT / ".." / "shared" / "reference" / "opensim" / "arm26.osim"
OSIM_REPO_PATH = "Models/Arm26/arm26.osim"  # of oracle_csv.OPENSIM_MODELS
DEFAULT_OUT = REPO_ROOT / "tests" / "data" / "arm26_elbow_oracle.csv"

MUSCLES = ("BRA", "TRImed")
ELBOW = "r_elbow_flex"
SHOULDER = "r_shoulder_elev"
ACTIVATION = 0.01  # the minimum Thelen activation: "passive" without a singular solve
COLUMNS = (
    "mtu_length_m",
    "moment_arm_m",
    "norm_fiber_length",
    "pennation_rad",
    "rigid_norm_fiber_length",
    "wrap_engaged",
)


def _wrap_engaged(osim, muscle, state) -> int:
    path = osim.GeometryPath.safeDownCast(muscle.getPath())
    points = path.getCurrentPath(state)
    return int(any(osim.PathWrapPoint.safeDownCast(points.get(i)) for i in range(points.getSize())))


def sweep(model_file: Path, angles_deg: np.ndarray) -> dict[str, np.ndarray]:
    """OpenSim lengths, normalised fibre lengths and moment arms at ``angles_deg``."""
    import opensim as osim

    model = osim.Model(str(model_file))
    state = model.initSystem()
    elbow = model.getCoordinateSet().get(ELBOW)
    out = {f"{m}_{c}": np.empty(angles_deg.shape) for m in MUSCLES for c in COLUMNS}
    for i, deg in enumerate(angles_deg):
        model.getCoordinateSet().get(SHOULDER).setValue(state, 0.0)
        elbow.setValue(state, math.radians(float(deg)))
        for name in MUSCLES:
            model.getMuscles().get(name).setActivation(state, ACTIVATION)
        model.equilibrateMuscles(state)
        model.realizeDynamics(state)
        for name in MUSCLES:
            mus = osim.Thelen2003Muscle.safeDownCast(model.getMuscles().get(name))
            mtu_m = mus.getLength(state)
            out[f"{name}_mtu_length_m"][i] = mtu_m
            out[f"{name}_moment_arm_m"][i] = mus.computeMomentArm(state, elbow)
            out[f"{name}_norm_fiber_length"][i] = mus.getNormalizedFiberLength(state)
            out[f"{name}_pennation_rad"][i] = mus.getPennationAngle(state)
            out[f"{name}_wrap_engaged"][i] = _wrap_engaged(osim, mus, state)
            # Thelen2003Muscle refuses ignore_tendon_compliance, so ask its own
            # fixed-width pennation model for the fibre length at tendon = slack length.
            rigid_m = mus.getPennationModel().calcFiberLength(mtu_m, mus.getTendonSlackLength())
            out[f"{name}_rigid_norm_fiber_length"][i] = rigid_m / mus.getOptimalFiberLength()
    return out


def write_csv(path: Path, angles_deg: np.ndarray, data: dict[str, np.ndarray], header: str):
    names = ["elbow_flex_deg", "elbow_flex_rad"] + [f"{m}_{c}" for m in MUSCLES for c in COLUMNS]
    table = np.column_stack([angles_deg, np.radians(angles_deg)] + [data[n] for n in names[2:]])
    write_table(path, names, table, header)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--osim", type=Path, default=DEFAULT_OSIM,
                   help=osim_help(OSIM_REPO_PATH, DEFAULT_OSIM))
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help="CSV to write")
    p.add_argument("--step-deg", type=float, default=1.0, help="angle step, deg")
    args = p.parse_args(argv)
    missing = missing_osim(args.osim, OSIM_REPO_PATH)
    if missing:
        print(missing, file=sys.stderr)
        return 2
    try:
        import opensim as osim
    except ImportError:
        print("needs the optional opensim package: pip install -e '.[opensim]'", file=sys.stderr)
        return 2
    angles_deg = np.arange(0.0, 130.0 + 1e-9, args.step_deg)
    data = sweep(args.osim, angles_deg)
    header = (
        f"OpenSim {osim.__version__} oracle for BRA and TRImed of Arm26 (Holzbaur et al. 2005,"
        " CC BY 3.0)\n"
        "made by: python scripts/make_length_oracle.py (source: ../shared/reference/opensim/"
        "arm26.osim, not copied)\n"
        f"shoulder r_shoulder_elev 0; passive equilibrium at activation {ACTIVATION};"
        " rigid_* = tendon at slack length,"
        " OpenSim MuscleFixedWidthPennationModel\n"
        "units: m, rad; moment arm positive = flexor"
    )
    write_csv(args.out, angles_deg, data, header)
    print(f"wrote {args.out} ({angles_deg.size} angles)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
