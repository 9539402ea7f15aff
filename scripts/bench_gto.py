"""Cost of a tendon organ (Ib) step against a spindle step, per muscle, side by side.

Four figures in one run, each the median over ``--rounds`` rounds of the CPU time of this
thread (time the shared machine gives to other processes is not counted), in ns per muscle
per step:

- numpy, n = ``--n`` (4096) muscles, one call per step: ``spindle.step`` (HUMAN, 1 ms,
  the default method) against ``TendonOrgans.step`` (HUMAN, 1 ms);
- C, the same n, ``--steps`` steps in one call: ``CSpindleBatch.steps`` against
  ``CTendonOrgans.run``.

Inputs: lengths 1 +- 0.05 L0 and forces 200 +- 150 N, sinusoids with a phase per muscle.
Target (issue 24): GTO / spindle <= 0.1 in both.

Last line: ``bench_gto numpy_ratio=... c_ratio=...``.

Usage: ``PYTHONPATH=. python scripts/bench_gto.py [--n 4096] [--steps 50] [--rounds 5]``
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import spindle
from spindle import tendon_organ as gto
from spindle.tendon_organ_params import HUMAN as GTO_HUMAN

DT_S = 1e-3


def inputs(n: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    t = (np.arange(1, steps + 1) * DT_S)[:, None]
    phase = np.linspace(0, 2 * np.pi, n, endpoint=False)[None, :]
    return 1.0 + 0.05 * np.sin(2 * np.pi * 2 * t + phase), 200 + 150 * np.sin(
        2 * np.pi * 2 * t + phase)


def median_ns(fn, rounds: int, per: int, prepare=None) -> float:
    """Median CPU time of ``fn()`` in ns per ``per`` (``prepare()`` first, untimed)."""
    times = []
    for _ in range(rounds):
        if prepare is not None:
            prepare()
        t0 = time.thread_time()
        fn()
        times.append(time.thread_time() - t0)
    return float(np.median(times)) / per * 1e9


def numpy_figures(n: int, steps: int, rounds: int) -> tuple[float, float]:
    L, F = inputs(n, steps)
    gs = np.full(n, 50.0)
    gd = np.full(n, 50.0)

    def spindles() -> None:
        state = spindle.equilibrium_state(L[0], gd, gs, spindle.HUMAN)
        for row in L[1:]:
            spindle.step(state, row, gd, gs, DT_S, spindle.HUMAN)

    g2 = np.full(n, 179.5)

    def organs() -> None:
        bank = gto.TendonOrgans(g2, GTO_HUMAN, DT_S, force_N=F[0], n=n)
        for row in F[1:]:
            bank.step(row)

    per = n * (steps - 1)
    return median_ns(spindles, rounds, per), median_ns(organs, rounds, per)


def c_figures(n: int, steps: int, rounds: int) -> tuple[float, float]:
    from spindle.native.spindle import CSpindleBatch
    from spindle.native.tendon_organ import CTendonOrgans

    L, F = inputs(n, steps)
    gd, gs = np.full((steps - 1, n), 50.0), np.full((steps - 1, n), 50.0)
    rest = spindle.equilibrium_state(L[0], 50.0, 50.0, spindle.HUMAN)
    batch = CSpindleBatch(rest, spindle.HUMAN, DT_S)
    bank = CTendonOrgans(np.full(n, 179.5), GTO_HUMAN, DT_S, force_N=F[0])

    per = n * (steps - 1)
    return (median_ns(lambda: batch.steps(L[1:], gd, gs), rounds, per,
                      lambda: batch.load(rest)),
            median_ns(lambda: bank.run(F[1:]), rounds, per, lambda: bank.reset(F[0])))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=4096)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args(argv)
    ns_sp, ns_gto = numpy_figures(args.n, args.steps, args.rounds)
    print(f"numpy n={args.n}: spindle {ns_sp:8.1f} ns/muscle/step, GTO {ns_gto:6.1f}  "
          f"ratio {ns_gto / ns_sp:.3f}")
    cs_sp, cs_gto = c_figures(args.n, args.steps, args.rounds)
    print(f"C     n={args.n}: spindle {cs_sp:8.1f} ns/muscle/step, GTO {cs_gto:6.1f}  "
          f"ratio {cs_gto / cs_sp:.3f}")
    print(f"bench_gto numpy_ratio={ns_gto / ns_sp:.3f} c_ratio={cs_gto / cs_sp:.3f}")


if __name__ == "__main__":
    main()
