"""Accuracy and stability of the spindle integrators on the Mileusnic (2006) Fig. 3 protocol.

Command line: ``python scripts/spindle_accuracy.py [--quick] [--out DIR] [--jobs N]`` (the
full sweep takes a few minutes on 2 cores).

The protocol is 9 runs: a ramp-and-hold stretch 0.95 -> 1.08 L0 at 0.11, 0.66 and 1.55 L0/s
from t = 1.0 s, 3.3 s in all, with (gamma_dyn, gamma_stat) = (0, 0), (70, 0), (0, 70) pps held
from t = 0. Each method and internal step is run on all 9 at once (n = 9 columns) and compared
with the stiff reference (scipy Radau, rtol 1e-10) on the sample grid. :func:`run` writes
``accuracy_table.md`` and ``fig3_protocol.png``.
"""

from __future__ import annotations

import dataclasses
import math
import re
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
from tqdm import tqdm

import spindle
from spindle.reference import ramp_and_hold, solve_reference

START_L0, END_L0, RAMP_START_S, DURATION_S = 0.95, 1.08, 1.0, 3.3
SPEEDS_L0_S = (0.11, 0.66, 1.55)
DRIVES_PPS = ((0.0, 0.0), (70.0, 0.0), (0.0, 70.0))
STEPS_US = (10, 20, 50, 100, 200, 500, 1000, 2000)
REFERENCE_DT_S = 1e-3
# Largest stable step: scanned on this grid (ms), then bisected up to the first failure.
STABILITY_GRID_MS = (0.1, 0.2, 0.5, 1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8, 1.9, 2.0,
                     2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 15.0, 20.0)
BISECTIONS = 6
BOUND_PPS = 1000.0


@dataclasses.dataclass(frozen=True)
class Run:
    speed_L0_s: float
    gamma_dyn_pps: float
    gamma_stat_pps: float

    @property
    def ramp_end_s(self) -> float:
        return RAMP_START_S + (END_L0 - START_L0) / self.speed_L0_s

    @property
    def label(self) -> str:
        return (f"{self.speed_L0_s:g} L0/s, γd {self.gamma_dyn_pps:g}, "
                f"γs {self.gamma_stat_pps:g}")


def protocol_runs(speeds: Sequence[float]) -> list[Run]:
    return [Run(v, gd, gs) for v in speeds for gd, gs in DRIVES_PPS]


def time_grid(dt_s: float) -> np.ndarray:
    return np.arange(round(DURATION_S / dt_s) + 1) * dt_s


def ramp_samples(runs: Sequence[Run], t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact length (T, n) and velocity (T, n) of the analytic ramp-and-hold at ``t_s``.

    At a corner that falls on a sample the velocity jumps; the sample gets the mean of its
    one-sided limits (the central difference of the exact lengths there).
    """
    speed = np.array([r.speed_L0_s for r in runs])
    end = np.array([r.ramp_end_s for r in runs])
    t = t_s[:, None]
    length = START_L0 + speed * np.clip(t - RAMP_START_S, 0.0, end - RAMP_START_S)
    inside = (t > RAMP_START_S) & (t < end)
    corner = np.isclose(t, RAMP_START_S, rtol=0, atol=1e-9) | np.isclose(t, end, rtol=0,
                                                                         atol=1e-9)
    velocity = np.where(inside, speed, 0.0) + np.where(corner, 0.5 * speed, 0.0)
    return length, velocity


def unlimited(method: str) -> spindle.Method:
    """The named method without its step limit, to measure beyond it."""
    return dataclasses.replace(spindle.METHODS[method], max_step_s=math.inf)


def simulate_runs(runs: Sequence[Run], method: str, step_s: float,
                  dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Ia and II (T, n) of all runs at once, sampled every ``dt_s``, stepped at ``step_s``."""
    length, velocity = ramp_samples(runs, time_grid(dt_s))
    r = spindle.simulate(
        length, dt_s, velocity=velocity, method=unlimited(method), step=step_s,
        gamma_dyn=np.array([x.gamma_dyn_pps for x in runs]),
        gamma_stat=np.array([x.gamma_stat_pps for x in runs]),
    )
    return r.ia, r.ii


def reference_run(run: Run) -> tuple[np.ndarray, np.ndarray]:
    stim = ramp_and_hold(START_L0, END_L0, run.speed_L0_s, RAMP_START_S, DURATION_S,
                         run.gamma_dyn_pps, run.gamma_stat_pps)
    ref = solve_reference(stim, time_grid(REFERENCE_DT_S))
    return ref.ia, ref.ii


def accuracy_job(runs: Sequence[Run], method: str,
                 step_us: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Ia and II (T, n) on a grid of max(1 ms, step); None if the integration blew up."""
    step_s = step_us * 1e-6
    dt_s = max(REFERENCE_DT_S, step_s)  # a multiple of the step and of the reference grid
    try:
        with np.errstate(all="ignore"):
            return simulate_runs(runs, method, step_s, dt_s)
    except FloatingPointError:
        return None


def is_stable(runs: Sequence[Run], method: str, step_s: float) -> bool:
    """All runs finite and within +-BOUND_PPS when sampled and stepped every ``step_s``."""
    try:
        with np.errstate(all="ignore"):
            ia, ii = simulate_runs(runs, method, step_s, step_s)
    except FloatingPointError:
        return False
    return bool(np.all(np.abs(ia) < BOUND_PPS) and np.all(np.abs(ii) < BOUND_PPS))


def stability_job(runs: Sequence[Run], method: str,
                  grid_ms: Sequence[float]) -> tuple[float | None, float | None]:
    """(largest stable step, first unstable step) in seconds: the grid is scanned upwards to
    its first failure, and the gap below it bisected. None: no stable / no unstable step."""
    stable = None
    for h_ms in grid_ms:
        if not is_stable(runs, method, h_ms * 1e-3):
            unstable = h_ms * 1e-3
            break
        stable = h_ms * 1e-3
    else:
        return stable, None
    if stable is not None:
        for _ in range(BISECTIONS):
            mid = 0.5 * (stable + unstable)
            stable, unstable = (mid, unstable) if is_stable(runs, method, mid) else (stable, mid)
    return stable, unstable


def run_pool(jobs: dict[object, tuple[Callable, tuple, float]], workers: int) -> dict:
    """Run {key: (fn, args, cost)} in processes, largest cost first, with a progress bar."""
    results = {}
    order = sorted(jobs, key=lambda k: -jobs[k][2])
    with ProcessPoolExecutor(max_workers=workers) as pool, tqdm(
        total=sum(j[2] for j in jobs.values()), unit="step", unit_scale=True,
        desc="jobs", file=sys.stderr,
    ) as bar:
        futures = {pool.submit(jobs[k][0], *jobs[k][1]): k for k in order}
        for fut in as_completed(futures):
            key = futures[fut]
            results[key] = fut.result()
            bar.update(jobs[key][2])
    return results


def rms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


def fmt_step(s: float | None) -> str:
    return "—" if s is None else f"{s * 1e3:.4g} ms"


def markdown(runs: Sequence[Run], errors: dict, stability: dict, default: tuple[str, int],
             per_run: tuple[np.ndarray, ...]) -> str:
    lines = ["## Worst-run RMS error against the reference (pps, over 3.3 s)", "",
             "Steps above the method's `max_step_s` are marked * (simulate refuses them; "
             "measured with the limit lifted).", "",
             "| method | step (µs) | Ia RMS | worst Ia run | II RMS | worst II run |",
             "|---|---:|---:|---|---:|---|"]
    for (method, step_us), (e_ia, e_ii) in errors.items():
        mark = "*" if step_us * 1e-6 > spindle.METHODS[method].max_step_s * (1 + 1e-9) else ""
        i, j = int(np.argmax(e_ia)), int(np.argmax(e_ii))
        if not np.isfinite(e_ia).all():
            lines.append(f"| {method} | {step_us}{mark} | unstable | | unstable | |")
            continue
        lines.append(f"| {method} | {step_us}{mark} | {e_ia[i]:.3g} | {runs[i].label} | "
                     f"{e_ii[j]:.3g} | {runs[j].label} |")
    lines += ["", "## Largest stable step (all runs finite, |Ia|, |II| < "
              f"{BOUND_PPS:g} pps; grid {STABILITY_GRID_MS[0]:g}–{STABILITY_GRID_MS[-1]:g} ms "
              "then bisection)", "",
              "| method | max_step_s (package) | largest stable step | first unstable step |",
              "|---|---:|---:|---:|"]
    for method, (ok, bad) in stability.items():
        top = "" if bad is not None else " (whole grid stable)"
        lines.append(f"| {method} | {fmt_step(spindle.METHODS[method].max_step_s)} | "
                     f"{fmt_step(ok)}{top} | {fmt_step(bad)} |")
    method, step_us = default
    e_ia, e_ii, max_ia, max_ii, peak_ia = per_run
    lines += ["", f"## Per run: {method} at {step_us} µs (pps)", "",
              "| speed (L0/s) | γ dyn | γ stat | Ia RMS | II RMS | Ia max abs | II max abs "
              "| reference Ia peak |", "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for k, r in enumerate(runs):
        lines.append(f"| {r.speed_L0_s:g} | {r.gamma_dyn_pps:g} | {r.gamma_stat_pps:g} | "
                     f"{e_ia[k]:.3g} | {e_ii[k]:.3g} | {max_ia[k]:.3g} | {max_ii[k]:.3g} | "
                     f"{peak_ia[k]:.1f} |")
    return "\n".join(lines) + "\n"


def figure(path: Path, runs: Sequence[Run], speeds: Sequence[float], ref: tuple,
           sim: tuple, label: str) -> None:
    """FibreColumns = speeds; rows = length, Ia, II, error of ``sim`` against the reference."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = time_grid(REFERENCE_DT_S)
    length, _ = ramp_samples(runs, t)
    colours = ("k", "tab:red", "tab:blue")
    fig, axes = plt.subplots(4, len(speeds), figsize=(4.2 * len(speeds), 10), sharex=True,
                             squeeze=False, sharey="row")
    for col, speed in enumerate(speeds):
        ax_l, ax_ia, ax_ii, ax_err = axes[:, col]
        ax_l.set_title(f"{speed:g} L0/s")
        for k, r in enumerate(runs):
            if r.speed_L0_s != speed:
                continue
            c = colours[DRIVES_PPS.index((r.gamma_dyn_pps, r.gamma_stat_pps))]
            name = f"γd {r.gamma_dyn_pps:g}, γs {r.gamma_stat_pps:g}"
            if c == "k":
                ax_l.plot(t, length[:, k], c)
            ax_ia.plot(t, ref[0][:, k], c, lw=2.5, alpha=0.35, label=f"{name} reference")
            ax_ia.plot(t, sim[0][:, k], c, lw=0.9, ls="--", label=f"{name} {label}")
            ax_ii.plot(t, ref[1][:, k], c, lw=2.5, alpha=0.35)
            ax_ii.plot(t, sim[1][:, k], c, lw=0.9, ls="--")
            ax_err.plot(t, sim[0][:, k] - ref[0][:, k], c, lw=0.9, label=f"Ia, {name}")
            ax_err.plot(t, sim[1][:, k] - ref[1][:, k], c, lw=0.9, ls=":", label=f"II, {name}")
        ax_err.set_xlabel("time (s)")
    for ax, name in zip(axes[:, 0], ("length (L0)", "Ia (pps)", "II (pps)",
                                     f"{label} − ref (pps)"), strict=True):
        ax.set_ylabel(name)
    axes[1, 0].legend(fontsize=7, loc="upper left")
    axes[3, 0].legend(fontsize=7, loc="lower left", ncol=2)
    fig.suptitle(f"Mileusnic (2006) Fig. 3 protocol\nthick: Radau reference; dashed: {label}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclasses.dataclass(frozen=True)
class AccuracyNumbers:
    """What the experiment reports: worst-run RMS errors (pps) per (method, step in µs) as
    (Ia per run, II per run), (largest stable, first unstable) step in s per method (empty
    with ``quick``), and the tables (markdown)."""

    errors: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]]
    stability: dict[str, tuple[float | None, float | None]]
    table_md: str

    def summary_md(self) -> str:
        return re.sub(r"^## ", "### ", self.table_md, flags=re.MULTILINE)  # nest the headings


def sweep_jobs(runs: Sequence[Run], steps_us: Sequence[int],
               stability: bool) -> dict[object, tuple[Callable, tuple, float]]:
    """The reference, accuracy and (if ``stability``) stability jobs, each with its cost."""
    n_steps = DURATION_S * len(runs)
    jobs: dict[object, tuple[Callable, tuple, float]] = {
        ("ref", k): (reference_run, (r,), 2e5) for k, r in enumerate(runs)
    }
    for method in spindle.METHODS:
        for step_us in steps_us:
            jobs[("acc", method, step_us)] = (accuracy_job, (runs, method, step_us),
                                              n_steps / (step_us * 1e-6))
        if stability:
            jobs[("stab", method)] = (stability_job, (runs, method, STABILITY_GRID_MS), 3e5)
    return jobs


def run(out_dir: Path, quick: bool = False, jobs: int = 1) -> AccuracyNumbers:
    """Write ``accuracy_table.md`` and ``fig3_protocol.png`` into ``out_dir``; ``jobs`` worker
    processes (``quick``: 1 speed, 1 ms steps, no stability search)."""
    out_dir = Path(out_dir)
    speeds = SPEEDS_L0_S[2:] if quick else SPEEDS_L0_S
    steps_us = (1000,) if quick else STEPS_US
    runs = protocol_runs(speeds)
    default = (spindle.DEFAULT_METHOD.name, 1000)
    results = run_pool(sweep_jobs(runs, steps_us, stability=not quick), jobs)

    ref = tuple(np.column_stack([results[("ref", k)][i] for k in range(len(runs))])
                for i in (0, 1))
    errors = {}
    for method in spindle.METHODS:
        for step_us in steps_us:
            if results[("acc", method, step_us)] is None:
                errors[method, step_us] = (np.full(len(runs), np.inf),) * 2
                continue
            ia, ii = results[("acc", method, step_us)]
            stride = round(max(REFERENCE_DT_S, step_us * 1e-6) / REFERENCE_DT_S)
            errors[method, step_us] = (rms(ia, ref[0][::stride]), rms(ii, ref[1][::stride]))
    stability = {m: results[("stab", m)] for m in spindle.METHODS if ("stab", m) in results}
    sim = results[("acc", *default)]
    per_run = (*errors[default], np.abs(sim[0] - ref[0]).max(axis=0),
               np.abs(sim[1] - ref[1]).max(axis=0), ref[0].max(axis=0))

    out_dir.mkdir(parents=True, exist_ok=True)
    table = markdown(runs, errors, stability, default, per_run)
    (out_dir / "accuracy_table.md").write_text(table)
    figure(out_dir / "fig3_protocol.png", runs, speeds, ref, sim,
           f"{default[0]} {default[1]} µs")
    return AccuracyNumbers(errors, stability, table)
