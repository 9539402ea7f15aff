"""Throughput of the arm chain, numpy vs C backend, measured side by side; not a timed test.

    python scripts/bench_chain.py            # ~30 s
    python scripts/bench_chain.py --quick    # smoke variant, a few seconds

Every variant streams the same encoder trace (a 130 deg/s flexion-extension through the
noisy AX-12 model, with its invalid readings, default ChainConfig: trapezoidal spindles at
1 ms, 500 Hz samples) through ``ArmChain.push_counts`` one sample per call, or through
``push_counts_block`` in blocks of 10 samples (an env step of 20 ms) or in one block. The
variants take turns within each repeat, so machine load hits them alike; the figures are
medians over repeats. The last line is
``chain_samples_per_s_numpy=<f> chain_samples_per_s_c_block10=<f> speedup=<f>``
(speedup: C blocks of 10 over numpy single pushes, the numpy chain's own way to run).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable, Sequence

import numpy as np

from proprio_env.body.encoder import Encoder
from spindle.chain import ChainConfig, make_chain


def encoder_trace(duration_s: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    t = np.arange(0.0, duration_s, 1e-3)
    period = 2 * 90 / 130.0
    angle = 20 + 90 * (1 - np.abs(2 * ((t % period) / period) - 1))
    return Encoder(rng=seed).record(t, angle)


def runner(backend: str, block: int, t_s: np.ndarray, counts: np.ndarray) -> Callable[[], int]:
    """A function that runs the whole trace through a reset chain and returns the samples."""
    config = ChainConfig(backend=backend)
    angle0 = float(config.calibration.angle_deg(counts[0]))
    t_rest, c_rest = t_s[1:], counts[1:].astype(float)

    chain = make_chain(config)  # built once: only reset and pushes are timed

    def run() -> int:
        chain.reset(angle0, t_s[0])
        if block == 1:
            for t, x in zip(t_rest, c_rest, strict=True):
                chain.push_counts(t, x)
        else:
            for start in range(0, t_rest.size, block):
                chain.push_counts_block(t_rest[start:start + block], c_rest[start:start + block])
        assert chain.counters["accepted"] > 0.9 * t_rest.size
        return t_rest.size

    return run


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short trace, few repeats")
    parser.add_argument("--repeats", type=int, default=None)
    args = parser.parse_args(argv)
    duration_s = 0.5 if args.quick else 2.0
    repeats = args.repeats or (2 if args.quick else 5)
    t_s, counts = encoder_trace(duration_s)
    variants = {
        "numpy single": runner("numpy", 1, t_s, counts),
        "numpy block10": runner("numpy", 10, t_s, counts),
        "c single": runner("c", 1, t_s, counts),
        "c block10": runner("c", 10, t_s, counts),
        "c block-all": runner("c", t_s.size, t_s, counts),
    }
    variants["c single"]()  # build the library before timing
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(repeats):
        for name, run in variants.items():
            start = time.perf_counter()
            n = run()
            rates[name].append(n / (time.perf_counter() - start))
    median = {name: statistics.median(r) for name, r in rates.items()}
    print(f"trace: {t_s.size} encoder samples ({duration_s} s at ~500 Hz), {repeats} repeats, "
          "medians")
    for name, rate in median.items():
        print(f"  {name:14s} {rate:12.0f} samples/s  {1e6 / rate:9.2f} us/sample  "
              f"x{rate / median['numpy single']:8.1f} vs numpy single")
    speedup = median["c block10"] / median["numpy single"]
    print(f"chain_samples_per_s_numpy={median['numpy single']:.1f} "
          f"chain_samples_per_s_c_block10={median['c block10']:.1f} speedup={speedup:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
