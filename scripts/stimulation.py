"""The stimulator stage on the demo motion: rates -> pulse trains in every mode.

    python scripts/stimulation.py [--out DIR] [--duration S] [--seed N]

Writes ``stimulation.png`` and each mode's events (CSV and npz) into ``--out`` (default
``out/stimulation``) and prints the pulse counts. The experiment is
:mod:`proprio_env.experiments.stimulation`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from proprio_env.experiments import stimulation


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/stimulation"))
    parser.add_argument("--duration", type=float, default=6.0, help="seconds of motion")
    parser.add_argument("--seed", type=int, default=0, help="encoder noise seed")
    args = parser.parse_args(argv)
    if not args.duration > 0:
        parser.error(f"--duration={args.duration} must be > 0")
    print(stimulation.run(args.out, duration_s=args.duration, seed=args.seed).report())


if __name__ == "__main__":
    main()
