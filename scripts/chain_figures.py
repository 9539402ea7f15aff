"""Figures and numbers for two design choices of the chain: the length low-pass and the PI
predictor.

    python scripts/chain_figures.py [--out DIR] [--duration S]

Writes ``derivative_noise.png`` and ``predictor_overshoot.png`` into ``--out`` (default
``out/chain``) and prints the numbers; the experiments are
:mod:`proprio_env.experiments.chain_figures`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from proprio_env.experiments import chain_figures


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/chain"))
    parser.add_argument("--duration", type=float, default=3.0)
    args = parser.parse_args(argv)
    print(chain_figures.run(args.out, duration_s=args.duration).report())
    print(f"wrote {args.out / 'derivative_noise.png'} and {args.out / 'predictor_overshoot.png'}")


if __name__ == "__main__":
    main()
