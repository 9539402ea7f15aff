"""Figures and numbers of the Golgi tendon organ (Ib) model: ``docs/gto.md``.

    PYTHONPATH=. python scripts/gto_figures.py [--out DIR] [--quick]

Writes ``gto_ramp_hold.png``, ``gto_static.png``, ``gto_accuracy.png`` and
``gto_implementations.png`` into ``--out`` (default ``docs/img``) and prints the numbers; the
experiment is :mod:`proprio_env.experiments.gto`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from proprio_env.experiments import gto


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img"))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    print(gto.run(args.out, quick=args.quick).summary_md())


if __name__ == "__main__":
    main()
