"""The stimulator stage on the demo motion: the prosthesis chain's Ia and II of BRA and TRImed
encoded into pulse trains in every mode (docs/stimulation.md's figure and numbers).

The motion is the demo's (:mod:`proprio_env.experiments.demo`): the MuJoCo servo's
flexion-extension at ~130 deg/s read by the simulated AX-12 encoder (~500 Hz) and run through
``spindle.chain.run_chain``. Each sample's rates are held until the next sample
(:func:`~spindle.stimulation.intervals_from_times`) and encoded per mode on the default
channel map (:data:`~spindle.stimulation.ELBOW_SPINDLES`) and limits. :func:`run` writes
``stimulation.png`` (rates and pulse rasters, one panel per mode), ``stimulation_<mode>.csv``
/ ``.npz`` (the events) and returns the pulse counts against the rates' integrals.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from proprio_env.body.encoder import Encoder
from proprio_env.body.model import load_model
from proprio_env.body.servo_motion import drive_servo, triangle_deg
from spindle.chain import MUSCLES, run_chain
from spindle.stimulation import (
    ELBOW_SPINDLES,
    MODES,
    EncoderParams,
    StimConfig,
    afferent_rates,
    intervals_from_times,
    make_stimulator,
    plot_raster,
    save_csv,
    save_npz,
)


def demo_rates(duration_s: float = 6.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(sample times (T,), rates (T, channels) of :data:`ELBOW_SPINDLES`) of the demo's
    prosthesis chain on ``duration_s`` of servo motion, encoder noise seed ``seed``."""
    model = load_model()
    t_phys = np.arange(0.0, duration_s, model.opt.timestep)
    motion = drive_servo(triangle_deg(t_phys), model)
    t_s, counts = Encoder(rng=seed).record(motion.t_s, motion.angle_deg)
    trace = run_chain(t_s, counts=counts)
    rates = ELBOW_SPINDLES.gather(afferent_rates(MUSCLES, ia=trace.ia_pps, ii=trace.ii_pps))
    return t_s, rates


def encode_all(t_s: np.ndarray, rates: np.ndarray,
               backend: str = "auto") -> dict[str, tuple[np.ndarray, dict[str, int]]]:
    """mode -> (events, counters) of each mode's default configuration."""
    dt = intervals_from_times(t_s)
    out = {}
    for mode in MODES:
        stim = make_stimulator(StimConfig(params=EncoderParams(mode=mode)), backend,
                               t0_s=float(t_s[0]))
        out[mode] = (stim.run(rates, dt), stim.counters)
    return out


def plot(t_s: np.ndarray, rates: np.ndarray, encoded: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = ELBOW_SPINDLES.labels
    fig, axes = plt.subplots(len(encoded) + 1, 1, figsize=(11, 2.2 * (len(encoded) + 1)),
                             sharex=True)
    for k, label in enumerate(labels):
        axes[0].plot(t_s, rates[:, k], lw=0.9, label=label)
    axes[0].set_ylabel("rate (pps)")
    axes[0].legend(fontsize=7, ncol=4, loc="upper right")
    axes[0].set_title("prosthesis chain on the demo motion (HUMAN spindles)")
    window = t_s <= t_s[0] + 2.0
    for ax, (mode, (events, counters)) in zip(axes[1:], encoded.items(), strict=True):
        shown = events[events["time_s"] <= t_s[0] + 2.0]
        plot_raster(ax, shown, labels, t_s[window], rates[window], rate_scale_pps=60.0,
                    amplitude_range_uA=(30, 150))
        ax.set_title(f"{mode}: {counters['pulses']} pulses, tick height = amplitude, "
                     "line = rate", fontsize=9)
        ax.set_xlabel("")
    axes[-1].set_xlim(t_s[0], t_s[0] + 2.0)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclass(frozen=True)
class StimulationNumbers:
    """Per mode and channel: pulses delivered, and the integral of the requested rate."""

    out_dir: Path
    duration_s: float
    elapsed_s: float
    integral: dict[str, float]
    pulses: dict[str, dict[str, int]]
    counters: dict[str, dict[str, int]]

    def report(self) -> str:
        lines = [f"{self.duration_s:g} s of demo motion; encoded in {self.elapsed_s:.2f} s",
                 "channel       " + "".join(f"{m:>12s}" for m in self.pulses)
                 + "   integral of the rate"]
        for label, integral in self.integral.items():
            lines.append(f"{label:14s}" + "".join(f"{p[label]:12d}" for p in
                                                   self.pulses.values()) + f"   {integral:.1f}")
        for mode, counts in self.counters.items():
            lines.append(f"{mode}: {({k: v for k, v in counts.items() if v})}")
        return "\n".join(lines)

    def summary_md(self) -> str:
        return "```\n" + self.report() + "\n```\n"


def run(out_dir: Path, quick: bool = False, duration_s: float | None = None,
        seed: int = 0) -> StimulationNumbers:
    """Encode ``duration_s`` (default 6 s, ``quick`` 2 s) of the demo motion in every mode;
    write the figure and the events into ``out_dir``."""
    duration_s = (2.0 if quick else 6.0) if duration_s is None else duration_s
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_s, rates = demo_rates(duration_s, seed)
    start = time.perf_counter()
    encoded = encode_all(t_s, rates)
    elapsed = time.perf_counter() - start
    labels = ELBOW_SPINDLES.labels
    for mode, (events, _) in encoded.items():
        save_csv(out_dir / f"stimulation_{mode}.csv", events, labels)
        save_npz(out_dir / f"stimulation_{mode}.npz", events, labels)
    plot(t_s, rates, encoded, out_dir / "stimulation.png")
    integral = rates.T @ intervals_from_times(t_s)
    return StimulationNumbers(
        out_dir, duration_s, elapsed, dict(zip(labels, integral.tolist(), strict=True)),
        {m: {label: int(np.sum(ev["channel"] == k)) for k, label in enumerate(labels)}
         for m, (ev, _) in encoded.items()},
        {m: c for m, (_, c) in encoded.items()})
