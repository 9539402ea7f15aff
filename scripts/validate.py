"""Regenerate every validation figure and table of the seed paper's Section IV, in one command.

    python scripts/validate.py [--out DIR] [--quick] [--no-progress] [--jobs N]

Steps (each into its own sub-folder of ``--out``, default ``out/validation``):

- ``human_gains``: how far fusimotor drive moves Ia and II, HUMAN vs CAT (table, figure);
- ``ecrb``: the human ECRB wrist protocol (the paper's Fig. 6) and the ECRB curve;
- ``obstruction``: obstructed movement (the paper's Fig. 7), template from the measured and
  from the intended motion;
- ``spindle_accuracy``: the Mileusnic Fig. 3 protocol accuracy table and panels
  (``scripts/spindle_accuracy.py``);
- ``length_fits``: the fitted BRA/TRImed lengths against MuJoCo and OpenSim
  (``scripts/fit_lengths.py``; the fits are written into the output folder, the committed
  ``models/length_fits.json`` is left alone);
- ``demo``: the chain demo figure (``scripts/demo.py``).

``--quick`` is the reduced run of the test suite (about half a minute): shorter motions, one
Fig. 3 speed at the default step, no stability search. ``summary.md`` collects every step's
numbers; ``logs/`` holds what each step printed. Needs the ``demo`` extra (matplotlib, tqdm,
scipy).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from functools import partial
from pathlib import Path

SCRIPTS = Path(__file__).resolve().parent
REPO_ROOT = SCRIPTS.parent
if str(REPO_ROOT) not in sys.path:  # run from a checkout without installing
    sys.path.insert(0, str(REPO_ROOT))

from proprio_env.validation.runner import PACKAGE_STEPS, Step, run_steps  # noqa: E402


def _script(name: str, *args: str) -> str:
    """Run ``scripts/<name>.py`` with ``args`` in a fresh interpreter; return its output (also
    printed into the step's log). A non-zero exit raises with the script's last lines."""
    run = subprocess.run([sys.executable, str(SCRIPTS / f"{name}.py"), *args],
                         capture_output=True, text=True, cwd=REPO_ROOT)
    print(run.stdout)
    print(run.stderr, file=sys.stderr)
    if run.returncode != 0:
        tail = "\n".join((run.stdout + run.stderr).strip().splitlines()[-5:])
        raise RuntimeError(f"{name}.py exited with status {run.returncode}:\n{tail}")
    return run.stdout


def spindle_accuracy_step(out_dir: Path, quick: bool, jobs: int = 1) -> str:
    args = ["--out", str(out_dir), "--jobs", str(jobs)]
    _script("spindle_accuracy", *args, *(["--quick"] if quick else []))
    table = (out_dir / "accuracy_table.md").read_text()
    return re.sub(r"^## ", "### ", table, flags=re.MULTILINE)  # nest its headings


def length_fits_step(out_dir: Path, quick: bool) -> str:
    _script("fit_lengths", "--fits", str(out_dir / "length_fits.json"),
            "--out", str(out_dir / "length_fits.png"))
    doc = json.loads((out_dir / "length_fits.json").read_text())
    rows = [f"- {m}: Chebyshev degree {e['degree']}, max error {e['max_error_L0']:.1e} L0 "
            f"against the exact MuJoCo lengths" for m, e in doc["muscles"].items()]
    return "\n".join(rows) + "\n"


def demo_step(out_dir: Path, quick: bool) -> str:
    text = _script("demo", "--out", str(out_dir), "--duration", "1.5" if quick else "6")
    return "```\n" + text.strip() + "\n```\n"


def script_steps(jobs: int = 1) -> tuple[Step, ...]:
    """The steps that run the scripts beside this one (``jobs``: accuracy sweep workers)."""
    return (
        Step("spindle_accuracy", "Spindle accuracy on the Mileusnic Fig. 3 protocol",
             partial(spindle_accuracy_step, jobs=jobs)),
        Step("length_fits", "Length fits (the paper's Fig. 5)", length_fits_step),
        Step("demo", "Chain demo (the paper's Fig. 8)", demo_step),
    )


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
    steps = (*PACKAGE_STEPS, *script_steps(args.jobs))
    run_steps(steps, args.out, quick=args.quick, progress=not args.no_progress)
    print((args.out / "summary.md").read_text())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
