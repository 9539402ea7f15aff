"""Regenerate the ECRB length table of the wrist, ``models/wrist_ecrb.csv``, with OpenSim.

Needs the optional ``opensim`` package (``pip install -e .[opensim]``); nothing at run time
does: the table is committed and :mod:`proprio_env.experiments.ecrb` reads it. Run::

    git clone --depth 1 https://github.com/opensim-org/opensim-models
    python scripts/make_wrist_oracle.py --osim opensim-models/Models/WristModel/wrist.osim
    python scripts/make_wrist_oracle.py --osim path/to/wrist.osim --out other.csv

The model is OpenSim's ``Models/WristModel/wrist.osim`` of
https://github.com/opensim-org/opensim-models;
without ``--osim`` the maintainers' copy in ../shared/reference/opensim/ is used.

Model: OpenSim's wrist model (Gonzalez, Buchanan & Delp 1997). For every wrist flexion
angle -70..70 deg (1 deg steps; positive = flexion, deviation 0, elbow and forearm at their
defaults) the coordinate couplers of the carpal rows are satisfied by ``assemble`` and the
muscles are equilibrated passively (activation 0.01). Per angle it writes ECRB's

- ``ECRB_mtu_length_m`` - musculotendon (path) length, m
- ``ECRB_norm_fiber_length`` - fibre length / optimal fibre length at passive equilibrium
  (elastic tendon): the curve the validation uses
- ``ECRB_pennation_rad`` - pennation angle at passive equilibrium, rad
- ``ECRB_moment_arm_flexion_m`` - moment arm about ``flexion``, m
- ``ECRB_rigid_norm_fiber_length`` - rigid tendon (tendon = slack length), constant-width
  pennation: sqrt((mtu - slack)^2 + (L0 sin alpha0)^2) / L0

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
DEFAULT_OSIM = REPO_ROOT / ".." / "shared" / "reference" / "opensim" / "wrist.osim"
OSIM_REPO_PATH = "Models/WristModel/wrist.osim"  # of oracle_csv.OPENSIM_MODELS
DEFAULT_OUT = REPO_ROOT / "models" / "wrist_ecrb.csv"

MUSCLE = "ECRB"
FLEXION = "flexion"
ACTIVATION = 0.01  # the muscles' min_control: "passive" without a singular solve
COLUMNS = (
    "mtu_length_m",
    "norm_fiber_length",
    "pennation_rad",
    "moment_arm_flexion_m",
    "rigid_norm_fiber_length",
)


def sweep(model_file: Path, angles_deg: np.ndarray) -> dict[str, np.ndarray]:
    """ECRB lengths, moment arm and normalised fibre lengths at wrist flexion ``angles_deg``."""
    import opensim as osim

    model = osim.Model(str(model_file))
    state = model.initSystem()
    flexion = model.getCoordinateSet().get(FLEXION)
    muscle = model.getMuscles().get(MUSCLE)
    L0 = muscle.getOptimalFiberLength()
    slack = muscle.getTendonSlackLength()
    width = L0 * math.sin(muscle.getPennationAngleAtOptimalFiberLength())
    out = {c: np.empty(angles_deg.shape) for c in COLUMNS}
    for i, deg in enumerate(angles_deg):
        flexion.setValue(state, math.radians(float(deg)))  # enforces the couplers (assemble)
        got = flexion.getValue(state)
        if abs(got - math.radians(float(deg))) > 1e-9:
            raise RuntimeError(f"assembly moved flexion from {deg} deg to {math.degrees(got)}")
        for m in range(model.getMuscles().getSize()):
            model.getMuscles().get(m).setActivation(state, ACTIVATION)
        model.equilibrateMuscles(state)
        model.realizeDynamics(state)
        mtu = muscle.getLength(state)
        out["mtu_length_m"][i] = mtu
        out["norm_fiber_length"][i] = muscle.getFiberLength(state) / L0
        out["pennation_rad"][i] = muscle.getPennationAngle(state)
        out["moment_arm_flexion_m"][i] = muscle.computeMomentArm(state, flexion)
        out["rigid_norm_fiber_length"][i] = math.hypot(mtu - slack, width) / L0
    return out


def write_csv(path: Path, angles_deg: np.ndarray, data: dict[str, np.ndarray], header: str):
    names = ["wrist_flexion_deg"] + [f"{MUSCLE}_{c}" for c in COLUMNS]
    table = np.column_stack([angles_deg] + [data[c] for c in COLUMNS])
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
    angles_deg = np.arange(-70.0, 70.0 + 1e-9, args.step_deg)
    data = sweep(args.osim, angles_deg)
    header = (
        f"OpenSim {osim.__version__} ECRB table of the wrist model (Gonzalez, Buchanan & Delp"
        " 1997)\n"
        "made by: python scripts/make_wrist_oracle.py (source: ../shared/reference/opensim/"
        "wrist.osim, not copied)\n"
        f"wrist flexion positive, deviation 0; passive equilibrium at activation {ACTIVATION};"
        " rigid_* = tendon at slack length, constant-width pennation\n"
        "units: m, rad; norm_* in optimal fibre lengths (L0)"
    )
    write_csv(args.out, angles_deg, data, header)
    print(f"wrote {args.out} ({angles_deg.size} angles)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
