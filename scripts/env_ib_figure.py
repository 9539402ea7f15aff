"""The v1 envs' tendon forces and Ib over an episode: ``docs/img/env_ib.png`` (docs/envs.md).

    PYTHONPATH=. python scripts/env_ib_figure.py [--out docs/img/env_ib.png]

The experiment is :mod:`proprio_env.experiments.env_ib`; it prints a table of the figures.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from proprio_env.experiments import env_ib


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img/env_ib.png"))
    args = parser.parse_args(argv)
    traces = [env_ib.run_trace(i) for i in ("proprio_env/ElbowReach-v1",
                                            "proprio_env/ProsthesisElbow-v1")]
    print(env_ib.summary(traces))
    print(f"wrote {env_ib.figure(traces, args.out)}")


if __name__ == "__main__":
    main()
