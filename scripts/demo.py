"""The whole chain on the bundled elbow: servo motion -> encoder, load -> Ia, II, Ib (the main job).

    python scripts/demo.py [--out DIR] [--duration S] [--seed N]

Writes ``demo.png`` (one column per muscle) and ``demo_signals.csv`` (every signal) into
``--out`` (default ``out/demo``) and prints the numbers. The experiment (the seed paper's
Fig. 8 protocol) is :mod:`proprio_env.experiments.demo`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from proprio_env.experiments import demo


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    parser.add_argument("--duration", type=float, default=6.0, help="seconds of motion")
    parser.add_argument("--seed", type=int, default=0, help="encoder noise seed")
    args = parser.parse_args(argv)
    if not args.duration > 0:
        parser.error(f"--duration={args.duration} must be > 0")
    print(demo.run(args.out, duration_s=args.duration, seed=args.seed).report())


if __name__ == "__main__":
    main()
