"""SB3 PPO training throughput: one env (SB3's own DummyVecEnv around ``gym.make``, the path
before the vector env) vs the native vector env through ``SB3VectorEnv``, side by side in one
process (docs/envs.md).

    python scripts/bench_train.py [--timesteps 40960] [--repeats 2] [--num-envs 1 8]

Every variant trains PPO with the documented settings (2048 env steps per update, torch on
one thread, the C chain) for ``--timesteps`` env steps; the variants alternate within each
repeat so that load drift hits all of them. Prints one line per run and, last,
``vector_<n>_vs_single=<ratio>`` per vector env count (medians of env steps/s over repeats,
PPO updates included). Needs the ``train`` extra.
"""

from __future__ import annotations

import argparse
import statistics
import time

from proprio_env.training.sb3 import (
    ROLLOUT_STEPS,
    make_env,
    make_vector_env,
    sb3_ppo_kwargs,
    training_ranges,
)
from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND


def train_steps_per_s(num_envs: int | None, timesteps: int, backend: str) -> float:
    """Env steps/s of PPO.learn (``num_envs`` None: one env through SB3's DummyVecEnv)."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import VecMonitor

    from proprio_env.training.sb3_vec import SB3VectorEnv

    kwargs = {"backend": backend}
    if num_envs is None:
        env = Monitor(make_env("proprio_env/ElbowReach-v0", kwargs, training_ranges(), seed=0))
        ppo_kwargs = sb3_ppo_kwargs(1)
    else:
        env = VecMonitor(SB3VectorEnv(make_vector_env("proprio_env/ElbowReach-v0", kwargs,
                                                      num_envs, training_ranges())))
        ppo_kwargs = sb3_ppo_kwargs(num_envs)
    model = PPO("MlpPolicy", env, seed=0, verbose=0, device="cpu", **ppo_kwargs)
    start = time.perf_counter()
    model.learn(timesteps)
    wall_s = time.perf_counter() - start
    env.close()
    return model.num_timesteps / wall_s


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--timesteps", type=int, default=20 * ROLLOUT_STEPS)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--backend", choices=BACKEND_CHOICES, default=DEFAULT_BACKEND)
    args = parser.parse_args(argv)
    if args.timesteps < 1 or args.repeats < 1:
        parser.error("--timesteps and --repeats must be positive")
    for n in args.num_envs:
        try:
            sb3_ppo_kwargs(n)
        except ValueError as exc:
            parser.error(str(exc))
    import torch

    torch.set_num_threads(1)
    variants: list[int | None] = [None, *args.num_envs]
    rates: dict[str, list[float]] = {}
    for repeat in range(args.repeats):
        for n in variants:
            name = "single" if n is None else f"vector_{n}"
            rate = train_steps_per_s(n, args.timesteps, args.backend)
            rates.setdefault(name, []).append(rate)
            print(f"repeat {repeat} {name}: {rate:.0f} env steps/s (PPO updates included)",
                  flush=True)
    single = statistics.median(rates["single"])
    print(" ".join(f"{name}_vs_single={statistics.median(r) / single:.2f}"
                   for name, r in rates.items() if name != "single"))
    return rates


if __name__ == "__main__":
    main()
