"""Cost of a tendon organ (Ib) step against a spindle step, per muscle, side by side.

Figures in one run, each the median over ``--rounds`` rounds of the CPU time of this thread
(time the shared machine gives to other processes is not counted), in ns per muscle per step
(the cases of numpy, then of C, one after the other in each round: :func:`median_ns`):

- numpy, n = ``--n`` (4096) muscles, one call per step: ``spindle.step`` (HUMAN, 1 ms,
  the default method) against ``TendonOrgans.step`` (HUMAN, 1 ms);
- C, the same n, ``--steps`` steps in one call: ``CSpindleBatch.steps`` against
  ``CTendonOrgans.run`` (its SIMD lanes in the best instruction set the CPU has: AVX-512,
  AVX2 or the baseline); and ``ps_gto_batch_run`` on the same states and forces in three
  builds of ``tendon_organ.c`` compiled side by side with the library's flags
  (:data:`BUILDS`): without the AVX-512 copy (what a CPU with AVX2 alone runs), the lanes in
  the baseline instruction set (SSE2), the scalar loop of ``ps_gto_step`` (no lanes).

Inputs: lengths 1 +- 0.05 L0 and forces 200 +- 150 N, sinusoids with a phase per muscle.
Target (issue 24): GTO / spindle <= 0.1 in both.

Last line: ``bench_gto numpy_ratio=... c_ratio=... c_avx2_ratio=...``.

Usage: ``PYTHONPATH=. python scripts/bench_gto.py [--n 4096] [--steps 50] [--rounds 5]``
"""

from __future__ import annotations

import argparse
import ctypes
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import spindle
from spindle import tendon_organ as gto
from spindle.tendon_organ_params import HUMAN as GTO_HUMAN

DT_S = 1e-3
BUILDS = {"avx2": "-DPS_GTO_LANES_NO_AVX512", "sse2": "-DPS_GTO_LANES_NO_AVX2",
          "scalar": "-DPS_GTO_BATCH_SCALAR"}


def inputs(n: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    t = (np.arange(1, steps + 1) * DT_S)[:, None]
    phase = np.linspace(0, 2 * np.pi, n, endpoint=False)[None, :]
    return 1.0 + 0.05 * np.sin(2 * np.pi * 2 * t + phase), 200 + 150 * np.sin(
        2 * np.pi * 2 * t + phase)


def median_ns(cases: dict, rounds: int, per: int) -> dict[str, float]:
    """Median CPU time of each case's ``fn()`` in ns per ``per``; ``cases`` maps a name to
    ``(fn, prepare)`` (``prepare()`` first, untimed, or None). Each case once per round, so
    that a busy spell of the shared machine hits all, each round starting one case further
    on (a case right after another finds its data in cache)."""
    names = list(cases)
    times: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        for name in names[r % len(names):] + names[:r % len(names)]:
            fn, prepare = cases[name]
            if prepare is not None:
                prepare()
            t0 = time.thread_time()
            fn()
            times[name].append(time.thread_time() - t0)
    return {name: float(np.median(t)) / per * 1e9 for name, t in times.items()}


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

    out = median_ns({"spindle": (spindles, None), "gto": (organs, None)}, rounds,
                    n * (steps - 1))
    return out["spindle"], out["gto"]


def variant_library(directory: Path, define: str) -> ctypes.CDLL:
    """``tendon_organ.c`` alone, with the library's flags and ``define``."""
    from spindle.native import build
    from spindle.native.tendon_organ import library

    out = directory / f"libgto{define}.so"
    subprocess.run([*build.compiler_command(), *build.compile_flags("double"), define, "-I",
                    str(build.SOURCE_DIR), str(build.SOURCE_DIR / "tendon_organ.c"), "-o",
                    str(out), "-lm"], check=True, capture_output=True)
    lib = ctypes.CDLL(str(out))
    lib.ps_gto_batch_run.argtypes = library().ps_gto_batch_run.argtypes
    return lib


def c_figures(n: int, steps: int, rounds: int) -> dict[str, float]:
    """ns per muscle and step: the spindle, the GTO as shipped, and each of :data:`BUILDS`."""
    from spindle.native.spindle import CSpindleBatch
    from spindle.native.tendon_organ import CTendonOrgans, PsGto

    L, F = inputs(n, steps)
    gd, gs = np.full((steps - 1, n), 50.0), np.full((steps - 1, n), 50.0)
    rest = spindle.equilibrium_state(L[0], 50.0, 50.0, spindle.HUMAN)
    batch = CSpindleBatch(rest, spindle.HUMAN, DT_S)
    bank = CTendonOrgans(np.full(n, 179.5), GTO_HUMAN, DT_S, force_N=F[0])
    start = bytes(bank._states)
    states = (PsGto * n).from_buffer_copy(start)
    forces = np.ascontiguousarray(F[1:])
    ib = np.empty_like(forces)
    per = n * (steps - 1)
    cases = {"spindle": (lambda: batch.steps(L[1:], gd, gs), lambda: batch.load(rest)),
             "gto": (lambda: bank.run(F[1:]),  # states back as the spindle's load does
                     lambda: ctypes.memmove(bank._states, start, len(start)))}
    with tempfile.TemporaryDirectory() as tmp:
        for name, define in BUILDS.items():
            lib = variant_library(Path(tmp), define)
            cases[name] = (
                lambda lib=lib: lib.ps_gto_batch_run(
                    ctypes.addressof(states), n, ctypes.byref(bank.plan), steps - 1,
                    forces.ctypes.data, bank.force_scale_N.ctypes.data, ib.ctypes.data, None),
                lambda: ctypes.memmove(states, start, len(start)))
        out = median_ns(cases, rounds, per)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=4096)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args(argv)
    ns_sp, ns_gto = numpy_figures(args.n, args.steps, args.rounds)
    print(f"numpy n={args.n}: spindle {ns_sp:8.1f} ns/muscle/step, GTO {ns_gto:6.1f}  "
          f"ratio {ns_gto / ns_sp:.3f}")
    c = c_figures(args.n, args.steps, args.rounds)
    print(f"C     n={args.n}: spindle {c['spindle']:8.1f} ns/muscle/step, GTO {c['gto']:6.1f}  "
          f"ratio {c['gto'] / c['spindle']:.3f}")
    for name, define in BUILDS.items():
        print(f"C     n={args.n}: GTO {name:6s} ({define}) {c[name]:6.1f}  "
              f"ratio {c[name] / c['spindle']:.3f}")
    print(f"bench_gto numpy_ratio={ns_gto / ns_sp:.3f} c_ratio={c['gto'] / c['spindle']:.3f} "
          f"c_avx2_ratio={c['avx2'] / c['spindle']:.3f}")

if __name__ == "__main__":
    main()
