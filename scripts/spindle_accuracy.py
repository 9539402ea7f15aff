"""Accuracy and stability of the spindle integrators on the Mileusnic (2006) Fig. 3 protocol.

    python scripts/spindle_accuracy.py                 # full sweep, a few minutes on 2 cores
    python scripts/spindle_accuracy.py --quick         # smoke test: 1 speed, 1 ms steps only
    python scripts/spindle_accuracy.py --out DIR --jobs 2

Writes ``accuracy_table.md`` and ``fig3_protocol.png`` into DIR (default
``out/spindle_accuracy``). The experiment is :mod:`proprio_env.experiments.spindle_accuracy`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from proprio_env.experiments import spindle_accuracy

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "out" / "spindle_accuracy"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--quick", action="store_true", help="1 speed, 1 ms steps, no stability "
                    "search (smoke test)")
    ap.add_argument("--jobs", type=int, default=min(os.cpu_count() or 1, 4))
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error(f"--jobs={args.jobs} must be >= 1")
    start = time.perf_counter()
    numbers = spindle_accuracy.run(args.out, quick=args.quick, jobs=args.jobs)
    print(numbers.table_md)
    print(f"wrote {args.out / 'accuracy_table.md'} and {args.out / 'fig3_protocol.png'}")
    print(f"total runtime {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
