"""Regenerate every validation figure and table of the seed paper's Section IV, in one command.

    python scripts/validate.py [--out DIR] [--quick] [--no-progress] [--jobs N]

Steps (each into its own sub-folder of ``--out``, default ``out/validation``), the modules
of :mod:`proprio_env.experiments`:

- ``human_gains``: how far fusimotor drive moves Ia and II, HUMAN vs CAT (table, figure);
- ``ecrb``: the human ECRB wrist protocol (the paper's Fig. 6) and the ECRB curve;
- ``obstruction``: obstructed movement (the paper's Fig. 7), template from the measured and
  from the intended motion;
- ``spindle_accuracy``: the Mileusnic Fig. 3 protocol accuracy table and panels;
- ``length_fits``: the fitted BRA/TRImed lengths against MuJoCo and OpenSim (the fits are
  written into the output folder, the committed ``models/length_fits.json`` is left alone);
- ``demo``: the chain demo figure (the paper's Fig. 8).

``--quick`` is the reduced run of the test suite (about half a minute): shorter motions, one
Fig. 3 speed at the default step, no stability search. ``summary.md`` collects every step's
numbers; ``logs/`` holds what each step printed. Needs the ``demo`` extra (matplotlib, tqdm,
scipy).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO_ROOT))

from proprio_env.experiments.runner import run_steps, validation_steps  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "validation")
    p.add_argument("--quick", action="store_true", help="reduced run (the test suite's)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--jobs", type=int, default=1,
                   help="worker processes of the spindle accuracy sweep (default 1)")
    args = p.parse_args(argv)
    if args.jobs < 1:
        p.error(f"--jobs={args.jobs} must be >= 1")
    run_steps(validation_steps(args.jobs), args.out, quick=args.quick,
              progress=not args.no_progress)
    print((args.out / "summary.md").read_text())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
