"""Regenerate ``models/moment_arm_fits.json``: MuJoCo's elbow moment arms every 0.5 deg.

    PYTHONPATH=. python scripts/fit_moment_arms.py [--out PATH] [--model elbow.xml]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from proprio_env.body.moment_arm_fitting import write_moment_arm_fits


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--model", type=Path, default=None)
    args = p.parse_args(argv)
    path = write_moment_arm_fits(args.out, args.model)
    doc = json.loads(path.read_text())
    for name, fit in doc["fits"].items():
        print(f"{name}: {len(fit['table_m'])} angles, interpolation error "
              f"{fit['max_error_m'] * 1e3:.5f} mm")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
