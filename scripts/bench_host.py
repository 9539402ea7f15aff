"""Host speed of the C spindle: ns per step and wall time per simulated second, vs numpy.

One spindle, the default setting (trapezoidal rule, 1 ms step, CAT constants), driven by a
smooth elbow-like length trace (0.9-1.1 L0 at 0.5-1.7 Hz, drive 30/30 pps) sampled at 1 kHz.
Figures, each the median of --repeats runs measured side by side in this process:

- ns_per_step: one ps_spindle_run call over the whole trace (the C loop alone);
- ms_per_simulated_s: spindle.simulate(..., backend="c") end to end (validation, sub-step
  lengths, ctypes call), per simulated second; the same for backend="numpy";
- speedup_vs_myogen: 52 ms per simulated second (myogen's spindle, a published figure, not measured
  side by side) / ms_per_simulated_s;
- rms_pps: the accuracy of this setting, worst-run RMS of Ia and II over the 9 runs of the
  Mileusnic Fig. 3 protocol against the stiff reference (spindle.reference, scipy Radau),
  simulated with backend="c".

Usage:  PYTHONPATH=. python scripts/bench_host.py [--seconds 20] [--repeats 7] [--quick]
The last line reads
    ns_per_step=<f> ms_per_simulated_s=<f> speedup_vs_myogen=<f> rms_pps=<f> c_vs_numpy=<f>
(c_vs_numpy: simulate's numpy time / its C time, the two measured side by side)
"""

from __future__ import annotations

import argparse
import ctypes
import statistics
import time
from collections.abc import Sequence

import numpy as np

import spindle
from spindle.native import abi
from spindle.native import spindle as native_spindle

MYOGEN_MS_PER_SIMULATED_S = 52.0
DT_S = 1e-3
SPEEDS = (0.11, 0.66, 1.55)
DRIVES = ((0.0, 0.0), (70.0, 0.0), (0.0, 70.0))


def elbow_trace(seconds: float) -> np.ndarray:
    t = np.arange(round(seconds / DT_S) + 1) * DT_S
    return 1.0 + 0.07 * np.sin(2 * np.pi * 0.5 * t) + 0.03 * np.sin(2 * np.pi * 1.7 * t + 1.0)


def median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def c_loop_seconds(length: np.ndarray, repeats: int) -> float:
    """Median wall time of one ps_spindle_run over the trace (1 step per sample)."""
    lib = native_spindle.library("double")
    p = abi.params_struct(spindle.CAT)
    _, PsSpindle = abi.structs("double")
    L = np.ascontiguousarray(length[1:])
    gd = np.full_like(L, 30.0)
    gs = np.full_like(L, 30.0)
    ia = np.empty_like(L)
    ii = np.empty_like(L)
    ptr = ctypes.POINTER(ctypes.c_double)
    args = [x.ctypes.data_as(ptr) for x in (L, gd, gs)]
    outs = [x.ctypes.data_as(ptr) for x in (ia, ii)]
    done = ctypes.c_long()

    def run():
        s = PsSpindle()
        code = lib.ps_spindle_init(ctypes.byref(s), ctypes.byref(p), length[0], 30.0, 30.0)
        if code != abi.Status.PS_OK:
            raise RuntimeError(f"init failed: {abi.status_name(code)}")
        code = lib.ps_spindle_run(ctypes.byref(s), ctypes.byref(p), *args, len(L), DT_S, 0.5,
                                  1, *outs, ctypes.byref(done))
        if code != abi.Status.PS_OK:
            raise RuntimeError(abi.status_name(code))

    run()
    return median_time(run, repeats)


def fig3_rms(quick: bool) -> float:
    from spindle.reference import ramp_and_hold, solve_reference

    speeds = (1.55,) if quick else SPEEDS
    t = np.arange(round(3.3 / DT_S) + 1) * DT_S
    worst = 0.0
    for speed in speeds:
        for gd, gs in DRIVES:
            stim = ramp_and_hold(speed_L0_s=speed, gamma_dyn_pps=gd, gamma_stat_pps=gs)
            ref = solve_reference(stim, t)
            length = np.array([stim.length_L0(x) for x in t])
            velocity = np.array([stim.velocity_L0_s(x) for x in t])
            r = spindle.simulate(length, DT_S, velocity=velocity, gamma_dyn=gd, gamma_stat=gs,
                                 backend="c")
            for got, want in ((r.ia, ref.ia), (r.ii, ref.ii)):
                worst = max(worst, float(np.sqrt(np.mean((got - want) ** 2))))
    return worst


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per run")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--quick", action="store_true",
                    help="accuracy on the 3 fastest-ramp runs only, fewer repeats")
    args = ap.parse_args(argv)
    repeats = 3 if args.quick else args.repeats
    length = elbow_trace(args.seconds)
    n_steps = len(length) - 1
    simulated_s = n_steps * DT_S

    def sim(backend: str):
        return lambda: spindle.simulate(length, DT_S, gamma_dyn=30.0, gamma_stat=30.0,
                                        backend=backend)

    a = sim("numpy")()
    b = sim("c")()
    agree = max(np.abs(a.ia - b.ia).max(), np.abs(a.ii - b.ii).max())
    t_loop = c_loop_seconds(length, repeats)
    t_c = median_time(sim("c"), repeats)
    t_np = median_time(sim("numpy"), max(1, repeats // 2))
    ns_per_step = t_loop / n_steps * 1e9
    ms_c = t_c / simulated_s * 1e3
    ms_np = t_np / simulated_s * 1e3
    rms = fig3_rms(args.quick)
    print(f"one spindle, trapezoidal 1 ms, CAT, {simulated_s:g} s simulated, medians of "
          f"{repeats} runs; numpy and C agree to {agree:.2g} pps on this trace")
    print(f"C loop (ps_spindle_run):           {ns_per_step:10.1f} ns/step "
          f"({t_loop / simulated_s * 1e3:.3f} ms per simulated s)")
    print(f"simulate(backend='c'):             {ms_c:10.3f} ms per simulated s")
    print(f"simulate(backend='numpy'):         {ms_np:10.3f} ms per simulated s")
    print(f"C / numpy speedup (simulate):      {ms_np / ms_c:10.1f}x")
    print(f"vs myogen's published {MYOGEN_MS_PER_SIMULATED_S:g} ms per simulated s (a figure "
          f"from elsewhere, not run here): {MYOGEN_MS_PER_SIMULATED_S / ms_c:.1f}x")
    print(f"accuracy: worst-run RMS vs the stiff reference (scipy Radau, run here) on Fig. 3 "
          f"({'1.55 L0/s runs' if args.quick else '9 runs'}): {rms:.3f} pps")
    print(f"ns_per_step={ns_per_step:.2f} ms_per_simulated_s={ms_c:.4f} "
          f"speedup_vs_myogen={MYOGEN_MS_PER_SIMULATED_S / ms_c:.1f} rms_pps={rms:.4f} "
          f"c_vs_numpy={ms_np / ms_c:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
