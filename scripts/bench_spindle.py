"""Throughput of the numpy spindle (default method, 1 ms step); a script, not a timed test.

    PYTHONPATH=. python scripts/bench_spindle.py                     # this tree, 1-2 min
    PYTHONPATH=. python scripts/bench_spindle.py --quick             # smoke variant, seconds
    PYTHONPATH=. python scripts/bench_spindle.py --baseline e4a47d8  # beside a git revision
    PYTHONPATH=. python scripts/bench_spindle.py --paths          # the step's implementations

1. spindle-steps per second for n = 1, 64, 4096, 65536 spindles, stepping
   ``spindle.core.advance`` + ``commit`` + ``afferents_from_tension`` in a loop: each spindle
   follows its own smooth length trajectory within 0.8-1.2 L0 and its own smooth fusimotor
   drive, starting at rest (``equilibrium_state``) at its first length and drive. Inputs are
   precomputed; only the spindle calls are timed. Median over repeats, of wall time and of
   this process's CPU time (the machine may be shared; CPU time is what one core spends).
2. wall time per simulated second of one spindle through ``spindle.simulate`` at default
   settings (1 s of a smooth trajectory sampled at 1 ms).

With ``--baseline REV`` (a git revision of this repository, e.g. e4a47d8, the core before
the throughput work; default none) the same measurements run on ``spindle/core.py`` and
``spindle/simulate.py`` of that git revision, loaded into temporary modules, interleaved
repeat by repeat with this tree's, and the ratios are printed together with the largest
difference in Ia/II between the two (same inputs).

With ``--paths`` it instead times this tree's implementations of the step side by side, CPU
time per step (advance + commit) on the same trajectories, best of 5:
``spindle.core.plain_advance`` (the step written plainly), ``spindle.float_step.advance_small``
(Python floats) and ``spindle.batch_step.advance_batched`` (numpy blocks), and the afferent
rates on numpy and on floats for a few spindles. These figures back the comments that keep
the second implementations (``spindle.core.advance``, ``spindle.core.afferents_from_tension``).

The comparison printed at the end is of runs side by side in this process: 65536 spindles
stepped together against one spindle alone (spindle-steps per second), and this tree against
the baseline when there is one. myogen's published speed (a Cython Mileusnic implementation:
~19 simulated spindle-seconds per wall second, 52 ms per simulated second for one spindle at
25 us steps) is quoted beside it as what it is, a figure from elsewhere, not a run here. The
last line is ``spindle_steps_per_s_n65536=<float> ms_per_simulated_s_single=<float>
spindle_steps_per_s_n1=<float> ratio_n65536_to_n1=<float>`` (wall-time medians of this
tree).
"""

from __future__ import annotations

import argparse
import importlib
import io
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
import timeit
import types
from collections.abc import Sequence
from pathlib import Path

import numpy as np

import spindle
import spindle.simulation
from spindle import batch_step, core, float_step
from spindle.fibre_constants import step_constants

STEP_S = 1e-3
MYOGEN_MS_PER_SIMULATED_S = 52.0
MYOGEN_SPINDLE_S_PER_WALL_S = 19.0
MAX_ELEMENTS = 2**24  # inputs precomputed per run: steps * n <= this (n = 65536: 256 steps,
# long enough that the first steps from rest, smooth and served by a guess that needs three
# steps of history, do not set the figure)
DEFAULT_BASELINE = "none"
REPO = Path(__file__).resolve().parents[1]


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


def load_baseline(rev: str) -> tuple[types.ModuleType, types.ModuleType]:
    """``spindle.core`` and ``spindle.simulate`` of git revision ``rev``, imported from that
    revision's whole ``spindle`` package (extracted to a temporary folder), so a core split
    over several modules is measured as it was. This tree's modules are put back afterwards;
    the baseline's keep their own references to each other."""
    folder = Path(tempfile.mkdtemp(prefix=f"bench_spindle_{rev}_"))
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "spindle"],
                             check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    ours = {name: m for name, m in sys.modules.items() if name.split(".")[0] == "spindle"}
    for name in ours:
        del sys.modules[name]
    sys.path.insert(0, str(folder))
    try:
        core_mod = importlib.import_module("spindle.core")
        try:
            simulate_mod = importlib.import_module("spindle.simulation")
        except ModuleNotFoundError:  # revisions before the module's rename
            simulate_mod = importlib.import_module("spindle.simulate")
    finally:
        sys.path.remove(str(folder))
        for name in [n for n in sys.modules if n.split(".")[0] == "spindle"]:
            del sys.modules[name]
        sys.modules.update(ours)
    return core_mod, simulate_mod


def run_steps(mod, length, gd, gs) -> tuple[float, float, np.ndarray, float]:
    """One timed run: (wall s, CPU s, the last step's (Ia, II), largest |Ia change| over the
    first step)."""
    theta = spindle.DEFAULT_METHOD.theta
    c = mod.columns(spindle.CAT)
    state = mod.equilibrium_state(length[0], gd[0], gs[0])
    ia0, _ = mod.afferents(state)
    # the afferents of the new tensions: afferents_from_tension (before the redesign, _afferents)
    afferents_from_tension = getattr(mod, "afferents_from_tension", None) or mod._afferents
    first = None
    w0, c0 = time.perf_counter(), time.process_time()
    for i in range(1, length.shape[0]):
        L, d, s = length[i], gd[i], gs[i]
        new = mod.advance(state, L, d, s, STEP_S, theta, c)
        mod.commit(state, new, L, d, s)
        ia, ii = afferents_from_tension(new[0], L, c)
        if first is None:
            first = ia
    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    if not (np.isfinite(ia).all() and np.isfinite(ii).all()):
        raise FloatingPointError("non-finite rates in the benchmark")
    return wall, cpu, np.stack((ia, ii)), float(np.abs(first - ia0).max())


def ms_per_simulated_second(sim) -> tuple[float, float]:
    """(wall ms, CPU ms) of simulate on 1 s of one spindle sampled at 1 ms."""
    length, gd, gs = trajectories(1, round(1.0 / STEP_S), seed=1)
    w0, c0 = time.perf_counter(), time.process_time()
    sim.simulate(length[:, 0], STEP_S, gamma_dyn=gd[:, 0], gamma_stat=gs[:, 0])
    return 1e3 * (time.perf_counter() - w0), 1e3 * (time.process_time() - c0)


def per_step_us(advance, n: int, steps: int) -> float:
    """CPU us per step of ``advance(state, L, gd, gs)`` + commit on :func:`trajectories`."""
    length, gd, gs = trajectories(n, steps)
    state = core.equilibrium_state(length[0], gd[0], gs[0])
    c0 = time.process_time()
    for i in range(1, steps + 1):
        core.commit(state, advance(state, length[i], gd[i], gs[i]), length[i], gd[i], gs[i])
    return (time.process_time() - c0) / steps * 1e6


def compare_paths() -> None:
    """The step's and the afferent rates' implementations side by side (``--paths``)."""
    theta = spindle.DEFAULT_METHOD.theta
    c = core.columns(spindle.CAT)
    k = step_constants(c, STEP_S, theta)
    paths = {
        "plain": lambda st, L, d, s: core.plain_advance(st, L, d, s, STEP_S, theta, c),
        "scalar": lambda st, L, d, s: float_step.advance_small(st, L, d, s, k),
        "batched": lambda st, L, d, s: batch_step.advance_batched(st, L, d, s, k),
    }
    for n, steps in ((1, 400), (2, 400), (8, 400), (64, 300), (4096, 60), (65536, 12)):
        names = [p for p in paths if p != "scalar" or n <= float_step.SMALL_N]
        us = {p: min(per_step_us(paths[p], n, steps) for _ in range(5)) for p in names}
        ratios = " ".join(f"plain/{p} = {us['plain'] / us[p]:.1f}x" for p in names[1:])
        print(f"n = {n:>5}: " + ", ".join(f"{p} {us[p]:.1f} us" for p in names) + f"; {ratios}")
    rng = np.random.default_rng(0)
    for n in (1, 2, float_step.SMALL_N):
        T, L = rng.uniform(0.0, 0.3, (3, n)), np.ones(n)
        floats = min(timeit.repeat(lambda T=T, L=L: core._afferents_floats(T, L, c),
                                   number=2000, repeat=5)) / 2000 * 1e6
        saved, core.SMALL_N = core.SMALL_N, 0  # the numpy form at any n
        try:
            array = min(timeit.repeat(lambda T=T, L=L: core.afferents_from_tension(T, L, c),
                                      number=2000, repeat=5)) / 2000 * 1e6
        finally:
            core.SMALL_N = saved
        print(f"afferents n = {n}: numpy {array:.1f} us, floats {floats:.1f} us "
              f"(floats {array / floats:.1f}x faster)")
    # the afferents in blocks or in one pass, where they run: after each step, whose arrays
    # have filled the cache (run_steps at n = 65536, CPU time, best of 4, interleaved)
    n = 65536
    length, gd, gs = trajectories(n, 128)
    times: dict[int, list[float]] = {core.AFFERENT_CHUNK: [], n: []}
    saved = core.AFFERENT_CHUNK
    try:
        for _ in range(4):
            for chunk, out in times.items():
                core.AFFERENT_CHUNK = chunk  # n: one pass
                out.append(run_steps(core, length, gd, gs)[1] / 128 * 1e3)
    finally:
        core.AFFERENT_CHUNK = saved
    blocked, one_pass = (min(x) for x in times.values())
    print(f"step + afferents n = {n}: afferents in blocks {blocked:.2f} ms per step, in one "
          f"pass {one_pass:.2f} ms ({one_pass / blocked:.3f}x)")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="few steps and repeats (smoke test)")
    ap.add_argument("--baseline", default=DEFAULT_BASELINE,
                    help="a git revision of this repository to run beside this tree (e.g. "
                         "e4a47d8, the core before the throughput work), or 'none' "
                         "(default %(default)s)")
    ap.add_argument("--repeats", type=int, default=None, help="repeats per size (default 5)")
    ap.add_argument("--paths", action="store_true",
                    help="time this tree's implementations of the step side by side instead")
    args = ap.parse_args(argv)
    if args.paths:
        compare_paths()
        return 0
    sizes = (1, 64, 4096, 65536)
    repeats = args.repeats or (1 if args.quick else 5)
    max_steps = 20 if args.quick else 2000
    impls = {"this tree": (core, sys.modules["spindle.simulation"])}
    if args.baseline != "none":
        impls[f"baseline {args.baseline}"] = load_baseline(args.baseline)
    m = spindle.DEFAULT_METHOD
    print(f"spindle package: {Path(spindle.__file__).parent}")
    print(f"method {m.name} (theta {m.theta}), step {STEP_S * 1e3:g} ms, median of {repeats} "
          "repeat(s), implementations interleaved repeat by repeat, alternating which goes first")
    print(f"{'n':>7} {'steps':>6} {'implementation':>18} {'steps/s wall':>13} "
          f"{'steps/s CPU':>12} {'us/step':>9} {'sim spindle-s/wall s':>21} {'|dIa| step 1':>13}")
    results: dict[tuple[int, str], tuple[float, float]] = {}
    for n in sizes:
        n_steps = max(5 if args.quick else 20, min(max_steps, MAX_ELEMENTS // n))
        length, gd, gs = trajectories(n, n_steps)
        walls: dict[str, list[float]] = {name: [] for name in impls}
        cpus: dict[str, list[float]] = {name: [] for name in impls}
        last, jump = {}, {}
        for repeat in range(repeats):
            # alternate which implementation runs first: the first of a pair measured a few
            # per cent slower at n = 65536 (cache and allocator state)
            order = list(impls.items())
            for name, (mod, _sim) in order[::-1] if repeat % 2 else order:
                wall, cpu, last[name], jump[name] = run_steps(mod, length, gd, gs)
                walls[name].append(n * n_steps / wall)
                cpus[name].append(n * n_steps / cpu)
        for name in impls:
            rate, rate_cpu = statistics.median(walls[name]), statistics.median(cpus[name])
            results[n, name] = rate, rate_cpu
            print(f"{n:>7} {n_steps:>6} {name:>18} {rate:>13.4g} {rate_cpu:>12.4g} "
                  f"{1e6 * n / rate:>9.1f} {rate * STEP_S:>21.4g} {jump[name]:>13.3g}")
        if len(impls) > 1:
            ours, base = (results[n, name] for name in impls)
            diff = np.abs(last["this tree"] - last[f"baseline {args.baseline}"]).max()
            print(f"{'':>7} {'':>6} {'ratio':>18} {ours[0] / base[0]:>13.2f} "
                  f"{ours[1] / base[1]:>12.2f}   (last step: max |d Ia, II| = {diff:.2g} pps)")
    singles: dict[str, list[tuple[float, float]]] = {name: [] for name in impls}
    for _, sim in impls.values():
        sim.simulate(np.ones(10), STEP_S)  # warm-up (imports, column cache)
    for _ in range(repeats):
        for name, (_, sim) in impls.items():
            singles[name].append(ms_per_simulated_second(sim))
    print("\nspindle.simulate, 1 spindle, 1 s at default settings (ms per simulated second):")
    ms = {}
    for name in impls:
        ms[name] = (statistics.median(x[0] for x in singles[name]),
                    statistics.median(x[1] for x in singles[name]))
        print(f"  {name:>18}: {ms[name][0]:8.1f} wall  {ms[name][1]:8.1f} CPU")
    ours = ms["this tree"]
    if len(impls) > 1:
        base = ms[f"baseline {args.baseline}"]
        print(f"  {'speed-up':>18}: {base[0] / ours[0]:8.2f} wall  {base[1] / ours[1]:8.2f} CPU")
    rate, rate_cpu = results[65536, "this tree"]
    rate_1, rate_cpu_1 = results[1, "this tree"]
    print("comparison, side by side in this run:")
    print(f"  65536 spindles stepped together make {rate / rate_1:.0f} x as many spindle-steps "
          f"per second as one spindle alone ({rate:.4g} vs {rate_1:.4g} wall; "
          f"{rate_cpu / rate_cpu_1:.0f} x per CPU second)")
    if len(impls) > 1:
        base_rate = results[65536, f"baseline {args.baseline}"][0]
        print(f"  this tree vs baseline {args.baseline} at n=65536: {rate / base_rate:.2f} x "
              "(table above for every n)")
    print(f"for reference, not measured here: myogen's published {MYOGEN_SPINDLE_S_PER_WALL_S:g} "
          f"simulated spindle-s per wall s and {MYOGEN_MS_PER_SIMULATED_S:g} ms per simulated s "
          f"for one spindle at 25 us steps; this run: {rate * STEP_S:.4g} spindle-s per wall s "
          f"at n=65536, {ours[0]:.1f} ms per simulated s for one spindle at "
          f"{STEP_S * 1e6:g} us steps")
    print(f"spindle_steps_per_s_n65536={rate:.6g} ms_per_simulated_s_single={ours[0]:.6g} "
          f"spindle_steps_per_s_n1={rate_1:.6g} ratio_n65536_to_n1={rate / rate_1:.6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
