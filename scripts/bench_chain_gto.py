"""What the force sense costs in the chain: a push with load words against the same push
without (a chain never given a load skips its tendon organs: they rest at zero force).

    PYTHONPATH=. python scripts/bench_chain_gto.py [--arms 4096] [--pushes 20]

One arm (``make_chain``) and a batch (``make_batched_chain``), numpy and C, with every arm's
samples at the same times (the tendon organs' step plan is then cached: numpy per interval,
C per arm while the interval repeats) and with 0.1 ms of per-arm jitter (a plan per distinct
interval). Prints ms per push side by side and the ratio.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from spindle.chain import ChainConfig, make_batched_chain, make_chain


def per_push_ms(n_arms: int, backend: str, with_load: bool, jitter_s: float,
                pushes: int) -> float:
    rng = np.random.default_rng(0)
    config = ChainConfig(backend=backend)
    loads = 300.0 + 200.0 * np.sin(np.arange(pushes + 1) * 0.3)
    if n_arms == 1:
        chain = make_chain(config)
        chain.reset(60.0, 0.0, load=loads[0] if with_load else None)
        t = np.cumsum(0.002 + rng.normal(0.0, jitter_s, pushes))
        start = time.perf_counter()
        for i in range(pushes):
            chain.push_counts(t[i], 500.0 + i % 5, loads[i + 1] if with_load else None)
        return (time.perf_counter() - start) / pushes * 1e3
    chain = make_batched_chain(n_arms, config)
    chain.reset(np.full(n_arms, 60.0), 0.0,
                load=np.full(n_arms, loads[0]) if with_load else None)
    t = np.zeros(n_arms)
    start = time.perf_counter()
    for i in range(pushes):
        t = t + 0.002 + rng.normal(0.0, jitter_s, n_arms)
        chain.push_counts(t, np.full(n_arms, 500.0 + i % 5),
                          load=np.full(n_arms, loads[i + 1]) if with_load else None)
    return (time.perf_counter() - start) / pushes * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arms", type=int, default=4096)
    parser.add_argument("--pushes", type=int, default=20)
    args = parser.parse_args()
    print(f"{'arms':>5} {'backend':>7} {'jitter':>7} {'with load':>10} {'no load':>9} ratio")
    for n, pushes in ((1, 50 * args.pushes), (args.arms, args.pushes)):
        for backend in ("numpy", "c"):
            for jitter in (0.0, 1e-4):
                a = per_push_ms(n, backend, True, jitter, pushes)
                b = per_push_ms(n, backend, False, jitter, pushes)
                print(f"{n:5d} {backend:>7} {jitter * 1e3:5.1f}ms {a:8.3f}ms {b:7.3f}ms "
                      f"{a / b:5.2f}")


if __name__ == "__main__":
    main()
