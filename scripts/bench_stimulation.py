"""Cost of the stimulator stage per channel per sample, beside the spindle's step per
spindle per sample, measured in one run; a script, not a timed test.

    PYTHONPATH=. python scripts/bench_stimulation.py [--seconds S] [--repeats N] [--m0plus]

Samples every 2 ms (the AX-12's ~500 Hz). The stimulator encodes smooth rates in 0-150 pps
(each channel its own phase) through ``make_stimulator(config, backend).run`` (numpy: a
loop of vectorised steps over the channels; C: one ``ps_stim_run`` call) for 4 channels
(the demo's map) and 16 (``PS_STIM_MAX_CHANNELS``), every mode. The spindle runs
``spindle.simulate`` (HUMAN, trapezoidal, its default 1 ms internal step: 2 sub-steps per
sample) for 4 and 16 spindles on smooth lengths, on numpy and on C. Each figure is the
median of ``--repeats`` wall-time runs divided by samples x channels (or spindles).

``--m0plus`` adds the Cortex-M0+ firmware (``firmware.c`` with ``FW_STIM``: the fixed-point
encoder and spindle step, emulated by :mod:`spindle.native.m0plus`; needs
``arm-none-eabi-gcc`` and unicorn): instructions per sample for the 4 channels, each mode,
beside the fixed-point spindle step's per muscle per sample (2 steps of 1 ms), in the same
firmware. The emulated events are checked against the host's fixed form on the way.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import spindle
from spindle.stimulation import MODES, EncoderParams, StimConfig, channel_map, make_stimulator

DT_S = 2e-3


def timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def rates(n: int, samples: int) -> np.ndarray:
    t = np.arange(samples)[:, None] * DT_S
    return 75.0 + 75.0 * np.sin(2 * np.pi * 0.7 * t + np.arange(n)[None, :])


def stimulator_cost(mode: str, n: int, samples: int, backend: str, repeats: int) -> float:
    config = StimConfig(channel_map([(f"M{k}", "ia") for k in range(n)]),
                        params=EncoderParams(mode=mode))
    r = rates(n, samples)

    def run():
        make_stimulator(config, backend).run(r, DT_S)

    return timed(run, repeats) / (samples * n)


def spindle_cost(n: int, samples: int, backend: str, repeats: int) -> float:
    t = np.arange(samples)[:, None] * DT_S
    length = 1.0 + 0.1 * np.sin(2 * np.pi * 0.7 * t + np.arange(n)[None, :])

    def run():
        spindle.simulate(length, DT_S, gamma_dyn=70.0, gamma_stat=70.0, params=spindle.HUMAN,
                         backend=backend)

    return timed(run, repeats) / (samples * n)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="simulated seconds per run")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--m0plus", action="store_true", help="also the Cortex-M0+ firmware")
    args = parser.parse_args(argv)
    samples = round(args.seconds / DT_S)
    print(f"{samples} samples of {DT_S * 1e3:g} ms, median of {args.repeats} runs, wall time")
    print(f"{'stage':26s}{'n':>4s}{'numpy (ns)':>14s}{'C (ns)':>10s}{'numpy/C':>9s}   per "
          "channel (spindle) per sample")
    for n in (4, 16):
        spin_np = spindle_cost(n, samples, "numpy", args.repeats)
        spin_c = spindle_cost(n, samples, "c", args.repeats)
        print(f"{'spindle step (HUMAN)':26s}{n:4d}{spin_np * 1e9:14.0f}{spin_c * 1e9:10.0f}"
              f"{spin_np / spin_c:9.1f}")
        for mode in MODES:
            np_s = stimulator_cost(mode, n, samples, "numpy", args.repeats)
            c_s = stimulator_cost(mode, n, samples, "c", args.repeats)
            print(f"{'stimulator ' + mode:26s}{n:4d}{np_s * 1e9:14.0f}{c_s * 1e9:10.0f}"
                  f"{np_s / c_s:9.1f}   C: {c_s / spin_c:.3f}x the C spindle step")
    if args.m0plus:
        m0plus(min(samples, 250))


def m0plus(samples: int) -> None:
    import tempfile

    from spindle.native import stimulation as cstim
    from spindle.native.m0plus import stim

    n = 4
    q = cstim.to_q16(rates(n, samples))
    dt_us = np.full(samples, round(DT_S * 1e6))
    print(f"\nCortex-M0+ (emulated, instructions; {samples} samples, {n} channels)")
    with tempfile.TemporaryDirectory() as build_dir:
        for mode in MODES:
            config = StimConfig(channel_map([(f"M{k}", "ia") for k in range(n)]),
                                params=EncoderParams(mode=mode))
            m = stim.emulate_stim(config, q, dt_us, build_dir)
            host, _ = cstim.fixed_run(config, q, dt_us)
            same = "same events as the host" if np.array_equal(m.events, host) else "DIFFER"
            print(f"stimulator {mode:11s} per sample mean {m.instructions.mean():7.0f} max "
                  f"{m.instructions.max():6d}, per channel {m.instructions.mean() / n:6.0f}; "
                  f"stack {m.stack_bytes} B; {same}")
        spin = stim.spindle_instructions(config, build_dir)
        print(f"spindle step (fixed, 1 ms) per muscle per sample mean {2 * spin.mean():7.0f} "
              f"max {2 * spin.max():6d}; firmware flash {m.flash_bytes} B, RAM {m.ram_bytes} B")


if __name__ == "__main__":
    main()
