"""Regenerate the reduced length model ``models/length_fits.json`` and its figure.

    python scripts/fit_lengths.py                      # writes models/length_fits.json
    python scripts/fit_lengths.py --out out/fig5.png   # figure path (default out/length_fits.png)

The sweep, fit and figure are :mod:`proprio_env.experiments.length_fits`. Exits non-zero if a
fit misses the 0.001 L0 target.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from proprio_env.body.length_fitting import (
    DEFAULT_MAX_DEGREE,
    DEFAULT_STEP_DEG,
    DEFAULT_TOLERANCE_L0,
    TARGET_L0,
)
from proprio_env.experiments.length_fits import DEFAULT_ORACLE, fit_and_draw

DEFAULT_FIGURE = Path(__file__).resolve().parents[1] / "out" / "length_fits.png"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=None, help="MJCF (default: models/elbow.xml)")
    p.add_argument("--fits", type=Path, default=None,
                   help="JSON to write (default: length_fits.json next to the model)")
    p.add_argument("--out", type=Path, default=DEFAULT_FIGURE, help="figure (PNG) to write")
    p.add_argument("--no-figure", action="store_true", help="skip the figure")
    p.add_argument("--oracle", type=Path, default=DEFAULT_ORACLE, help="OpenSim oracle CSV")
    p.add_argument("--step-deg", type=float, default=DEFAULT_STEP_DEG, help="sweep step, deg")
    p.add_argument("--tolerance", type=float, default=DEFAULT_TOLERANCE_L0,
                   help="held-out max error (L0) a degree must reach")
    p.add_argument("--max-degree", type=int, default=DEFAULT_MAX_DEGREE)
    args = p.parse_args(argv)

    figure = None if args.no_figure else args.out
    numbers = fit_and_draw(args.model, args.fits, figure, args.oracle, args.step_deg,
                           args.tolerance, args.max_degree)
    print(f"wrote {numbers.fits_file} (elbow.xml sha256 {numbers.model_sha256[:12]}...)")
    for name, entry in numbers.muscles.items():
        print(f"  {name}: degree {entry['degree']}, max error {entry['max_error_L0']:.2e} L0 "
              f"(held-out {entry['heldout_max_error_L0']:.2e} L0)")
    if figure is not None:
        print(f"wrote {figure}")
    if not numbers.within_target:
        print(f"a fit misses the {TARGET_L0} L0 target; raise --max-degree", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
