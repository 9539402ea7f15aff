"""RLlib PPO throughput with 1 and 2 env runners, measured side by side in one process on a
local Ray instance (docs/training.md).

    python scripts/bench_rllib.py [--iterations 4] [--repeats 2] [--num-envs-per-runner 8]

Each repeat builds the algorithm with 1 runner, then with 2 (alternating, so that load drift
hits both), trains one warm-up iteration and then ``--iterations`` iterations of 2048 env
steps, and records the env steps per second of whole iterations (sampling + PPO update) and
of the runners sampling alone (``EnvRunner.sample`` on every runner at once, the same number
of steps split over them). Prints one line per measurement and, last,
``runners_2_vs_1 iteration=<ratio> sampling=<ratio>`` (medians over repeats). Needs the
``distributed`` extra.
"""

from __future__ import annotations

import argparse
import statistics
import time

from proprio_env.training.rllib import (
    RLlibOptions,
    build_algorithm,
    env_steps,
    start_ray,
)
from proprio_env.training.sb3 import TrainConfig
from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND


def measure(num_runners: int, num_envs: int, iterations: int, backend: str) -> dict[str, float]:
    """Env steps/s of whole PPO iterations (sampling + update) and of the runners sampling
    alone (the same number of steps split over the runners, sampled in parallel), after one
    warm-up iteration."""
    config = TrainConfig(backend=backend, num_envs=num_envs)
    algo = build_algorithm(config, RLlibOptions(num_env_runners=num_runners))
    try:
        before = env_steps(algo.train())
        start = time.perf_counter()
        for _ in range(iterations):
            result = algo.train()
        wall_s = time.perf_counter() - start
        steps = env_steps(result) - before
        per_runner = steps // num_runners
        start = time.perf_counter()
        sampled = algo.env_runner_group.foreach_env_runner(
            lambda r: sum(len(e) for e in r.sample(num_timesteps=per_runner)),
            local_env_runner=False)
        sample_s = time.perf_counter() - start
    finally:
        algo.stop()
    return {"iteration_steps_per_s": steps / wall_s, "steps": steps, "wall_s": wall_s,
            "sampling_steps_per_s": sum(sampled) / sample_s}


def main(argv: list[str] | None = None) -> dict[int, list[dict[str, float]]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--num-envs-per-runner", type=int, default=8)
    parser.add_argument("--backend", choices=BACKEND_CHOICES, default=DEFAULT_BACKEND)
    args = parser.parse_args(argv)
    if args.iterations < 1 or args.repeats < 1:
        parser.error("--iterations and --repeats must be positive")
    import torch

    torch.set_num_threads(1)  # the PPO update runs here, on one thread as in train.py
    start_ray(RLlibOptions())
    runs: dict[int, list[dict[str, float]]] = {1: [], 2: []}
    for repeat in range(args.repeats):
        for runners in (1, 2):
            m = measure(runners, args.num_envs_per_runner, args.iterations, args.backend)
            runs[runners].append(m)
            print(f"repeat {repeat} runners={runners} x {args.num_envs_per_runner} envs: "
                  f"{m['steps']:.0f} steps in {m['wall_s']:.1f} s, "
                  f"iteration {m['iteration_steps_per_s']:.0f} env steps/s, "
                  f"sampling {m['sampling_steps_per_s']:.0f} env steps/s", flush=True)
    med = {k: {key: statistics.median(m[key] for m in v) for key in v[0]} for k, v in runs.items()}
    print(f"runners_2_vs_1 iteration="
          f"{med[2]['iteration_steps_per_s'] / med[1]['iteration_steps_per_s']:.2f} "
          f"sampling={med[2]['sampling_steps_per_s'] / med[1]['sampling_steps_per_s']:.2f}")
    return runs


if __name__ == "__main__":
    main()
