"""The force sense's cost in the envs: v1 (Ib observed) against v0, side by side.

    PYTHONPATH=. python scripts/bench_env_ib.py [--steps 1000] [--repeats 3] [--backend c]

Single envs, the same action every step, interleaved repeats; prints steps per CPU-second
(process time, so that other jobs on a shared machine count less) and the median ratio
v1 / v0 per env.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np


def steps_per_cpu_s(env_id: str, steps: int, backend: str) -> float:
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    env = gym.make(env_id, backend=backend)
    env.reset(seed=0)
    action = env.action_space.sample()
    start = time.process_time()
    for _ in range(steps):
        env.step(action)
    elapsed = time.process_time() - start
    env.close()
    return steps / elapsed


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backend", default="c", choices=("numpy", "c", "auto"))
    args = parser.parse_args(argv)
    import gymnasium  # noqa: F401  (its import sets its own warning filters: first)

    warnings.simplefilter("ignore", DeprecationWarning)  # Gymnasium: v0 beside v1
    for base in ("ElbowReach", "ProsthesisElbow"):
        rates: dict[str, list[float]] = {"v0": [], "v1": []}
        for _ in range(args.repeats):
            for version in rates:
                rates[version].append(steps_per_cpu_s(f"proprio_env/{base}-{version}",
                                                      args.steps, args.backend))
        v0, v1 = (float(np.median(rates[v])) for v in ("v0", "v1"))
        print(f"{base}: v0 {v0:,.0f} steps/CPU-s, v1 {v1:,.0f} steps/CPU-s, "
              f"v1 / v0 = {v1 / v0:.2f} ({args.backend}, {args.steps} steps, "
              f"median of {args.repeats})")


if __name__ == "__main__":
    main()
