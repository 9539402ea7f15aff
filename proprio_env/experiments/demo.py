"""The whole chain on the bundled elbow: servo motion -> encoder, load -> Ia, II, Ib (the main job).

As in the seed paper's Fig. 8: the MuJoCo elbow's position servo drives repeated rapid
flexion-extension (~130 deg/s, 20-110 deg). A simulated AX-12 encoder reads the angle
(~500 Hz, 0.29 deg counts, noise, jitter, rare glitches) and the prosthesis chain
(``spindle.chain``: median filter, f(x), fitted lengths, low-pass, fusimotor template,
gamma_s/gamma_d, HUMAN spindles) turns the readings into Ia and II of the brachialis (BRA)
and the triceps medial head (TRImed). Beside each angle the servo's load reading (the
simulated load word of the servo's joint torque, MuJoCo's actuator force) goes into the same
chain, which turns it into BRA and TRImed tendon forces and their Golgi tendon organs' Ib.
The bundled servo holds the Arm26 forearm against gravity with up to ~5 N m, above an
AX-12's 1.5 N m stall torque, so the demo's load word spans the model servo's force range
(:func:`proprio_env.body.servo_motion.servo_load_params`, 20 N m for 1023 counts) instead of
saturating.

Beside it, at the same sample times, two noise-free chains run on the motion MuJoCo really
made: one on the clean angle through the fitted lengths (reduced), one on MuJoCo's exact
tendon-derived fibre lengths (exact). The summary reports the exact-vs-reduced difference
(what the fitted length model costs) and the encoder-vs-clean difference (what the sensor
stage costs), in pps.

:func:`run` writes ``demo.png`` (one column per muscle), ``demo_signals.csv`` (every
signal) and ``demo_pulses.csv`` (the stimulator's pulse events: the rates of BRA and TRImed Ia,
II and Ib frequency-coded into charge-balanced pulses, ``spindle.stimulation``); the command
line is ``python scripts/demo.py [--out DIR] [--duration S] [--seed N]``.
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from proprio_env.body.encoder import Encoder, LoadSensor
from proprio_env.body.model import load_model
from proprio_env.body.servo_motion import drive_servo, servo_load_params, triangle_deg
from spindle.chain import MUSCLES, ChainConfig, ChainTrace, run_chain
from spindle.chain.sensor import Calibration
from spindle.stimulation import (
    ELBOW_ALL,
    StimConfig,
    afferent_rates,
    intervals_from_times,
    make_stimulator,
    plot_raster,
)
from spindle.stimulation.events import save_csv as save_pulses_csv

STIMULATION = StimConfig(channels=ELBOW_ALL)
"""The demo's stimulator: frequency coding of BRA and TRImed Ia, II and Ib, one channel each
(``docs/stimulation.md``)."""


def run_chains(duration_s: float, seed: int) -> dict[str, object]:
    """The servo motion, the encoder and load readings and the three chains' traces."""
    model = load_model()
    t_phys = np.arange(0.0, duration_s, model.opt.timestep)
    motion = drive_servo(triangle_deg(t_phys), model)

    encoder = Encoder(rng=seed)
    t_s, counts = encoder.record(motion.t_s, motion.angle_deg)
    true_angle = np.interp(t_s, motion.t_s, motion.angle_deg)
    true_torque = np.interp(t_s, motion.t_s, motion.torque_Nm)
    config = ChainConfig(load=servo_load_params(model))
    sensor = LoadSensor(config.load, sign=config.calibration.sign,
                        rng=np.random.default_rng([seed, 1]))
    load = sensor.read_block(true_torque)
    exact_L = np.stack([np.interp(t_s, motion.t_s, motion.length_L0[:, k]) for k in range(2)],
                       axis=-1)
    prosthesis = run_chain(t_s, counts=counts, load=load, config=config)
    reduced = run_chain(t_s, angle_deg=true_angle)
    exact = run_chain(t_s, length_L0=exact_L)
    rates = STIMULATION.channels.gather(afferent_rates(
        MUSCLES, ia=prosthesis.ia_pps, ii=prosthesis.ii_pps, ib=prosthesis.ib_pps))
    stimulator = make_stimulator(STIMULATION, t0_s=float(t_s[0]))
    events = stimulator.run(rates, intervals_from_times(t_s))  # each rate held to the next
    return {"t_s": t_s, "true_angle_deg": true_angle, "true_torque_Nm": true_torque,
            "load_counts": load, "exact_length_L0": exact_L,
            "prosthesis": prosthesis, "reduced": reduced, "exact": exact,
            "channel_rates_pps": rates, "pulses": events,
            "stimulator_counters": stimulator.counters}


def rms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


def write_csv(result: dict[str, object], path: Path) -> None:
    cols = {"t_s": result["t_s"], "true_angle_deg": result["true_angle_deg"],
            "true_torque_Nm": result["true_torque_Nm"]}
    for name, column in result["prosthesis"].columns().items():
        if name != "t_s":
            cols[name] = column
        if name == "counts_filtered":
            cols["load_counts"] = result["load_counts"]
    for name in ("reduced", "exact"):
        trace: ChainTrace = result[name]
        for k, muscle in enumerate(MUSCLES):
            cols[f"{name}_{muscle}_length_L0"] = trace.length_L0[:, k]
            cols[f"{name}_{muscle}_ia_pps"] = trace.ia_pps[:, k]
            cols[f"{name}_{muscle}_ii_pps"] = trace.ii_pps[:, k]
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(cols)
        writer.writerows(zip(*(np.asarray(v, dtype=float) for v in cols.values()), strict=True))


def plot(result: dict[str, object], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pro: ChainTrace = result["prosthesis"]
    exact: ChainTrace = result["exact"]
    t = result["t_s"]
    cal = Calibration()
    raw_deg = np.where(pro.counts >= 0, cal.angle_deg(pro.counts), np.nan)
    rows = ["encoder", "length", "gamma_s", "gamma_d", "ia", "ii", "torque", "force", "ib",
            "pulses"]
    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 19), sharex=True)
    for k, muscle in enumerate(MUSCLES):
        ax = axes[0, k]
        # the raw readings under the lines (they show where they leave them); the legend's
        # markerscale makes their entry visible
        ax.plot(t, raw_deg, ".", ms=2, color="0.55", label="encoder raw")
        ax.plot(t, pro.angle_deg, lw=1, label="median filtered, f(x)")
        ax.plot(t, result["true_angle_deg"], lw=0.8, ls="--", color="k", label="MuJoCo")
        ax.set_ylim(0, 130)
        ax.set_ylabel("elbow angle (deg)")
        ax.set_title(f"{muscle}", loc="right")
        ax = axes[1, k]
        ax.plot(t, pro.length_L0[:, k], label="fitted (encoder)")
        ax.plot(t, exact.length_L0[:, k], ls="--", lw=0.8, color="k", label="exact (MuJoCo)")
        ax.plot(t, pro.template_L0[:, k], lw=0.8, label="PI template")
        ax.set_ylabel("fibre length (L0)")
        axes[2, k].plot(t, pro.gamma_static_pps[:, k])
        axes[2, k].set_ylabel("γs (pps)")
        axes[3, k].plot(t, pro.gamma_dynamic_pps[:, k], drawstyle="steps-post")
        axes[3, k].set_ylabel("γd (pps)")
        for row, field in ((4, "ia_pps"), (5, "ii_pps")):
            ax = axes[row, k]
            ax.plot(t, getattr(pro, field)[:, k], lw=1, label="prosthesis chain (encoder)")
            ax.plot(t, getattr(exact, field)[:, k], lw=0.8, ls="--", color="k",
                    label="exact lengths, clean")
            ax.set_ylabel(("Ia" if row == 4 else "II") + " (pps)")
        ax = axes[6, k]
        ax.plot(t, pro.torque_Nm, lw=1, label="from the load reading")
        ax.plot(t, result["true_torque_Nm"], lw=0.8, ls="--", color="k",
                label="MuJoCo servo torque")
        ax.set_ylabel("joint torque (N m)")
        axes[7, k].plot(t, pro.force_N[:, k], lw=1)
        axes[7, k].set_ylabel("tendon force (N)")
        axes[8, k].plot(t, pro.ib_pps[:, k], lw=1, color="C3")
        axes[8, k].set_ylabel("Ib (pps)")
        channels = [STIMULATION.channels.index(muscle, a) for a in ("ia", "ii", "ib")]
        plot_raster(axes[9, k], result["pulses"], STIMULATION.channels.labels, t,
                    result["channel_rates_pps"], channels=channels)
        axes[9, k].set_ylabel("pulses")
        axes[-1, k].set_xlabel("time (s)")
    # legends above their panels, over no data, on both columns
    for row in (0, 1, 4, 5, 6):
        for k in range(2):
            axes[row, k].legend(fontsize=7, loc="lower left", bbox_to_anchor=(0.0, 1.0),
                                ncol=3, frameon=False, borderaxespad=0.1, markerscale=6)
    fig.suptitle("Seed paper Fig. 8 protocol: servo-driven flexion-extension at ~130°/s, "
                 "HUMAN spindles and tendon organs, frequency-coded pulses")
    fig.tight_layout(rect=(0, 0, 1, 0.985))
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclass(frozen=True)
class DemoNumbers:
    """What the demo reports: the run's size and time, the encoder handling counters and, per
    muscle, the prosthesis chain's Ia/II ranges (pps) and the exact-vs-reduced and
    encoder-vs-clean RMS differences (pps)."""

    out_dir: Path
    duration_s: float
    samples: int
    elapsed_s: float
    counters: dict[str, int]
    ia_range_pps: dict[str, tuple[float, float]]
    ii_range_pps: dict[str, tuple[float, float]]
    ib_range_pps: dict[str, tuple[float, float]]
    exact_vs_reduced_rms_pps: dict[str, tuple[float, float]]
    """muscle -> (Ia, II)"""
    encoder_vs_clean_rms_pps: dict[str, tuple[float, float]]
    """muscle -> (Ia, II)"""
    pulses: dict[str, tuple[int, float]]
    """stimulation channel -> (pulses delivered, the integral of its requested rate)"""
    stimulator_counters: dict[str, int]

    def report(self) -> str:
        lines = [f"{self.duration_s:g} s of servo motion, {self.samples} encoder samples "
                 f"({self.samples / self.duration_s:.0f} Hz), chains run in "
                 f"{self.elapsed_s:.1f} s",
                 f"encoder handling: {self.counters}"]
        for muscle in MUSCLES:
            (ia_lo, ia_hi), (ii_lo, ii_hi) = self.ia_range_pps[muscle], self.ii_range_pps[muscle]
            ex_ia, ex_ii = self.exact_vs_reduced_rms_pps[muscle]
            enc_ia, enc_ii = self.encoder_vs_clean_rms_pps[muscle]
            ib_lo, ib_hi = self.ib_range_pps[muscle]
            lines.append(f"{muscle:7s} Ia {ia_lo:5.1f}-{ia_hi:5.1f} pps, II {ii_lo:5.1f}-"
                         f"{ii_hi:5.1f} pps, Ib {ib_lo:5.1f}-{ib_hi:5.1f} pps"
                         f" | exact vs reduced RMS Ia {ex_ia:.3f}, II "
                         f"{ex_ii:.3f} pps | encoder vs clean RMS Ia {enc_ia:.2f}, II "
                         f"{enc_ii:.2f} pps")
        lines.append("pulses (frequency coding) vs the integral of the requested rate: "
                     + ", ".join(f"{label} {n} / {integral:.1f}"
                                 for label, (n, integral) in self.pulses.items()))
        lines.append(f"stimulator limits: {self.stimulator_counters}")
        lines.append(f"wrote {self.out_dir / 'demo.png'}, {self.out_dir / 'demo_signals.csv'} "
                     f"and {self.out_dir / 'demo_pulses.csv'}")
        return "\n".join(lines)

    def summary_md(self) -> str:
        return "```\n" + self.report() + "\n```\n"


def run(out_dir: Path, quick: bool = False, duration_s: float | None = None,
        seed: int = 0) -> DemoNumbers:
    """Run the chains on ``duration_s`` of servo motion (default 6 s, ``quick`` 1.5 s) with
    encoder noise seed ``seed``, and the stimulator on the prosthesis chain's rates; write
    ``demo.png``, ``demo_signals.csv`` and ``demo_pulses.csv`` into ``out_dir``."""
    if duration_s is None:
        duration_s = 1.5 if quick else 6.0
    if not duration_s > 0:
        raise ValueError(f"duration_s={duration_s!r} must be > 0")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    result = run_chains(duration_s, seed)
    elapsed = time.perf_counter() - start
    write_csv(result, out_dir / "demo_signals.csv")
    save_pulses_csv(out_dir / "demo_pulses.csv", result["pulses"], STIMULATION.channels.labels)
    plot(result, out_dir / "demo.png")
    # what frequency coding promises: the pulses of a channel over the run equal the integral
    # of its requested rate (each sample's rate held until the next) within one pulse
    dt = intervals_from_times(result["t_s"])
    integrals = (result["channel_rates_pps"] * dt[:, None]).sum(axis=0)
    delivered = np.bincount(result["pulses"]["channel"], minlength=len(STIMULATION.channels))
    pro, red, ex = result["prosthesis"], result["reduced"], result["exact"]
    ex_ia, ex_ii = rms(ex.ia_pps, red.ia_pps), rms(ex.ii_pps, red.ii_pps)
    enc_ia, enc_ii = rms(pro.ia_pps, red.ia_pps), rms(pro.ii_pps, red.ii_pps)
    return DemoNumbers(
        out_dir, duration_s, pro.t_s.size, elapsed,
        {k: v for k, v in pro.counters.items() if v},
        {m: (pro.ia_pps[:, k].min(), pro.ia_pps[:, k].max()) for k, m in enumerate(MUSCLES)},
        {m: (pro.ii_pps[:, k].min(), pro.ii_pps[:, k].max()) for k, m in enumerate(MUSCLES)},
        {m: (pro.ib_pps[:, k].min(), pro.ib_pps[:, k].max()) for k, m in enumerate(MUSCLES)},
        {m: (ex_ia[k], ex_ii[k]) for k, m in enumerate(MUSCLES)},
        {m: (enc_ia[k], enc_ii[k]) for k, m in enumerate(MUSCLES)},
        {label: (int(delivered[c]), float(integrals[c]))
         for c, label in enumerate(STIMULATION.channels.labels)},
        {k: v for k, v in result["stimulator_counters"].items() if v},
    )
