"""Throughput of the numpy spindle (default method, 1 ms step); a script, not a timed test.

    python scripts/bench_spindle.py            # ~1 min
    python scripts/bench_spindle.py --quick    # smoke variant, a few seconds

1. spindle-steps per second for n = 1, 64, 4096, 65536 spindles, stepping
   ``spindle.core.advance`` + ``commit`` + ``_afferents`` in a loop: each spindle follows its
   own smooth length trajectory within 0.8-1.2 L0 and its own smooth fusimotor drive, starting
   at rest (``equilibrium_state``) at its first length and drive. Inputs are precomputed; only
   the spindle calls are timed. Median over repeats.
2. wall time per simulated second of one spindle through ``spindle.simulate`` at default
   settings (1 s of a smooth trajectory sampled at 1 ms).

Compared with myogen (a faithful Cython Mileusnic implementation: ~19 simulated
spindle-seconds per wall second, i.e. 52 ms per simulated second for one spindle at 25 us
steps) and with the target of 5e6 spindle-steps/s at n = 65536. The last line is
``spindle_steps_per_s_n65536=<float> ms_per_simulated_s_single=<float>``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Sequence

import numpy as np

import spindle
from spindle import core

STEP_S = 1e-3
MYOGEN_MS_PER_SIMULATED_S = 52.0
MYOGEN_SPINDLE_S_PER_WALL_S = 19.0
TARGET_STEPS_PER_S_N65536 = 5e6
MAX_ELEMENTS = 2**22  # inputs precomputed per run: steps * n <= this


def trajectories(n: int, n_steps: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Length (L0), gamma_dyn and gamma_stat (pps), each (n_steps + 1, n).

    Per spindle, sums of cosines with their own centre, amplitudes and frequencies: every
    input starts with zero slope, so the spindle, which starts at rest, is at rest in a
    trajectory that is momentarily still (no start-up transient). L stays in [0.8, 1.2] L0,
    |dL/dt| <= ~1.3 L0/s, the drives in [0, 80] pps.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps + 1)[:, None] * STEP_S
    f = rng.uniform((0.3, 1.5, 0.1, 0.1), (1.5, 4.0, 1.0, 1.0), (n, 4)).T
    a1, a2 = rng.uniform(0.0, 0.12, n), rng.uniform(0.0, 0.05, n)
    centre = rng.uniform(0.8 + a1 + a2, 1.2 - a1 - a2)
    length = centre + a1 * np.cos(2 * np.pi * f[0] * t) + a2 * np.cos(2 * np.pi * f[1] * t)
    gd = rng.uniform(0, 80, n) * (0.5 + 0.5 * np.cos(2 * np.pi * f[2] * t))
    gs = rng.uniform(0, 80, n) * (0.5 + 0.5 * np.cos(2 * np.pi * f[3] * t))
    return length, gd, gs


def steps_per_second(n: int, n_steps: int, repeats: int) -> tuple[float, float, float]:
    """(median spindle-steps/s, largest |Ia change| over the first step, and over any step,
    pps)."""
    length, gd, gs = trajectories(n, n_steps)
    theta = spindle.DEFAULT_METHOD.theta
    c = core.columns(spindle.CAT)
    rates = []
    first_jump = max_jump = 0.0
    for _ in range(repeats):
        state = core.equilibrium_state(length[0], gd[0], gs[0])
        ia_prev, _ = core.afferents(state)
        changes = np.empty(n_steps)
        t0 = time.perf_counter()
        for i in range(1, n_steps + 1):
            L, d, s = length[i], gd[i], gs[i]
            new = core.advance(state, L, d, s, STEP_S, theta, c)
            core.commit(state, new, L, d, s)
            ia, ii = core._afferents(new[0], L, c)
            changes[i - 1] = np.abs(ia - ia_prev).max()
            ia_prev = ia
        rates.append(n * n_steps / (time.perf_counter() - t0))
        first_jump, max_jump = float(changes[0]), float(changes.max())
    if not (np.isfinite(ia).all() and np.isfinite(ii).all()):
        raise FloatingPointError("non-finite rates in the benchmark")
    return statistics.median(rates), first_jump, max_jump


def ms_per_simulated_second(repeats: int) -> float:
    """Median wall time (ms) of spindle.simulate on 1 s of one spindle sampled at 1 ms."""
    length, gd, gs = trajectories(1, round(1.0 / STEP_S), seed=1)
    spindle.simulate(length[:10, 0], STEP_S)  # warm-up (imports, column cache)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        spindle.simulate(length[:, 0], STEP_S, gamma_dyn=gd[:, 0], gamma_stat=gs[:, 0])
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="few steps and repeats (smoke test)")
    args = ap.parse_args(argv)
    sizes = (1, 64, 4096, 65536)
    repeats = 1 if args.quick else 5
    max_steps = 20 if args.quick else 2000
    m = spindle.DEFAULT_METHOD
    print(f"method {m.name} (theta {m.theta}), step {STEP_S * 1e3:g} ms, "
          f"median of {repeats} repeat(s)")
    print(f"{'n':>7} {'steps':>6} {'spindle-steps/s':>16} {'us/step':>9} "
          f"{'sim spindle-s/wall s':>21} {'|dIa| step 1 / max':>19}")
    results = {}
    for n in sizes:
        n_steps = max(5 if args.quick else 20, min(max_steps, MAX_ELEMENTS // n))
        rate, jump, max_jump = steps_per_second(n, n_steps, repeats)
        results[n] = rate
        print(f"{n:>7} {n_steps:>6} {rate:>16.4g} {1e6 * n / rate:>9.1f} "
              f"{rate * STEP_S:>21.4g} {jump:>9.2g} / {max_jump:<7.2g}")
    ms_single = ms_per_simulated_second(repeats)
    rate = results[65536]
    print(f"\nspindle.simulate, 1 spindle, 1 s at default settings: {ms_single:.1f} ms per "
          "simulated second")
    print("comparison:")
    print(f"  n=65536: {rate:.4g} spindle-steps/s = {rate / TARGET_STEPS_PER_S_N65536:.2f} x "
          f"the {TARGET_STEPS_PER_S_N65536:.0e} target; {rate * STEP_S:.4g} simulated "
          f"spindle-s per wall s = {rate * STEP_S / MYOGEN_SPINDLE_S_PER_WALL_S:.1f} x myogen's "
          f"{MYOGEN_SPINDLE_S_PER_WALL_S:g}")
    print(f"  single spindle: {ms_single:.1f} ms per simulated s vs myogen's "
          f"{MYOGEN_MS_PER_SIMULATED_S:g} ms (ratio myogen/ours = "
          f"{MYOGEN_MS_PER_SIMULATED_S / ms_single:.2f}; note myogen steps at 25 us, "
          f"we at {STEP_S * 1e6:g} us)")
    print(f"spindle_steps_per_s_n65536={rate:.6g} ms_per_simulated_s_single={ms_single:.6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
