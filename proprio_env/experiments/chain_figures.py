"""Figures and numbers for two design choices of the chain: the length low-pass and the PI
predictor.

1. ``derivative_noise.png``: what sensor noise does to the spindles with and without the
   tracking low-pass. The motion is the demo's 130 deg/s flexion-extension sampled at 500 Hz;
   Gaussian noise of 0.001-0.005 L0 is added to the fitted lengths. Unfiltered, the noisy
   lengths are differenced by the spindle itself (its input is the length change per step);
   filtered, they pass the chain's 20 Hz tracking low-pass first. Errors are RMS against the
   spindles driven by the clean lengths, unfiltered. The realistic encoder path (counts,
   median filter) is reported too.
2. ``predictor_overshoot.png``: the fusimotor template of the down-sampled PI predictor on a
   step and on a ramp that stops suddenly, with gamma_s and gamma_d.

Command line: ``python scripts/chain_figures.py [--out DIR]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

import spindle
from proprio_env.body.encoder import Encoder
from spindle.chain import ArmChain, ChainConfig, run_chain
from spindle.chain.fusimotor import SEED_PAPER, Fusimotor

NOISE_L0 = (0.001, 0.002, 0.005)
RATE_HZ = 500.0


def triangle(t_s: np.ndarray) -> np.ndarray:
    period = 2 * 90 / 130.0
    return 20 + 90 * (1 - np.abs(2 * ((t_s % period) / period) - 1))


def rms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


def noise_experiment(duration_s: float = 3.0, seed: int = 0) -> dict[str, object]:
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration_s, 1 / RATE_HZ)
    angle = triangle(t)
    clean_L = spindle.load_length_fits().length_L0(np.radians(angle))
    raw_cfg = ChainConfig(lowpass_hz=None, max_speed_L0_s=spindle.MAX_SPEED_L0_S)
    reference = run_chain(t, length_L0=clean_L, config=raw_cfg)
    rows = []
    traces = {}
    for sigma in NOISE_L0:
        noisy = np.clip(clean_L + sigma * rng.normal(size=clean_L.shape), 0.5, 1.5)
        raw = run_chain(t, length_L0=noisy, config=raw_cfg)
        filt = run_chain(t, length_L0=noisy)
        rows.append((f"length noise {sigma:g} L0", rms(raw.ia_pps, reference.ia_pps),
                     rms(raw.ii_pps, reference.ii_pps), rms(filt.ia_pps, reference.ia_pps),
                     rms(filt.ii_pps, reference.ii_pps)))
        traces[sigma] = (raw, filt)
    t_s, counts = Encoder(rng=seed).record(t, angle)
    ref_enc = run_chain(t_s, length_L0=spindle.load_length_fits().length_L0(
        np.radians(triangle(t_s))), config=raw_cfg)
    enc_raw = run_chain(t_s, counts=counts, config=raw_cfg)
    enc_filt = run_chain(t_s, counts=counts)
    rows.append(("AX-12 encoder + median", rms(enc_raw.ia_pps, ref_enc.ia_pps),
                 rms(enc_raw.ii_pps, ref_enc.ii_pps), rms(enc_filt.ia_pps, ref_enc.ia_pps),
                 rms(enc_filt.ii_pps, ref_enc.ii_pps)))
    clean_filt = run_chain(t, length_L0=clean_L)
    rows.append(("no noise (filter lag only)", np.zeros(2), np.zeros(2),
                 rms(clean_filt.ia_pps, reference.ia_pps),
                 rms(clean_filt.ii_pps, reference.ii_pps)))
    return {"t": t, "reference": reference, "traces": traces, "rows": rows}


def predictor_experiment() -> dict[str, np.ndarray]:
    chain = ArmChain()
    lo, hi = chain.length_min_L0, chain.length_max_L0
    fus = Fusimotor(lo, hi, SEED_PAPER)
    t = np.arange(0.0, 3.0, 2e-3)
    # BRA: rest, a 0.1 L0 step at 0.3 s, rest, a 0.5 L0/s ramp-down from 1.5 s stopping at 1.8 s
    base = 0.95
    L = np.where(t >= 0.3, base + 0.1, base)
    L = np.where(t >= 1.5, base + 0.1 - 0.5 * np.minimum(t - 1.5, 0.3), L)
    out = {"t": t, "input": L}
    fus.reset(np.zeros(1), np.array([[L[0], 0.8]]))
    inputs = np.stack((L, np.full_like(L, 0.8)), axis=-1)[None]  # one arm, (1, T, 2)
    template, gamma_s, gamma_d = fus.update(t[None], inputs)
    out["template"], out["gamma_s"], out["gamma_d"] = (x[0, :, 0] for x in (template, gamma_s,
                                                                           gamma_d))
    return out


def plot_noise(result: dict[str, object], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = result["t"]
    ref = result["reference"]
    raw, filt = result["traces"][0.002]
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=False)
    window = t < 1.5
    for ax, field, label in ((axes[0], "ia_pps", "Ia"), (axes[1], "ii_pps", "II")):
        ax.plot(t[window], getattr(raw, field)[window, 0], lw=0.6, color="0.6",
                label="noisy lengths, unfiltered")
        ax.plot(t[window], getattr(filt, field)[window, 0], lw=1,
                label="noisy, 20 Hz tracking filter")
        ax.plot(t[window], getattr(ref, field)[window, 0], lw=1, ls="--", color="k",
                label="clean lengths")
        ax.set_ylabel(f"BRA {label} (pps)")
        ax.set_xlabel("time (s)")
    axes[0].legend(fontsize=8)
    axes[0].set_title("130°/s flexion-extension, 0.002 L0 length noise at 500 Hz, HUMAN spindles")
    rows = result["rows"][: len(NOISE_L0)]
    ax = axes[2]
    sig = np.array(NOISE_L0)
    ax.semilogy(sig, [r[1].max() for r in rows], "o-", label="Ia, unfiltered")
    ax.semilogy(sig, [r[2].max() for r in rows], "s-", label="II, unfiltered")
    ax.semilogy(sig, [r[3].max() for r in rows], "o--", label="Ia, filtered")
    ax.semilogy(sig, [r[4].max() for r in rows], "s--", label="II, filtered")
    ax.set_xlabel("length noise (L0, standard deviation)")
    ax.set_ylabel("RMS error vs clean (pps, worse muscle)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_predictor(result: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = result["t"]
    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    axes[0].plot(t, result["input"], label="measured length")
    axes[0].plot(t, result["template"], label="PI template (50 Hz)")
    axes[0].set_ylabel("BRA length (L0)")
    axes[0].legend(fontsize=8)
    axes[0].set_title("Fusimotor template: a step at 0.3 s, a ramp stopping at 1.8 s")
    axes[1].plot(t, result["gamma_s"])
    axes[1].set_ylabel("γs (pps)")
    axes[2].plot(t, result["gamma_d"], drawstyle="steps-post")
    axes[2].set_ylabel("γd (pps)")
    axes[2].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


@dataclass(frozen=True)
class ChainFigureNumbers:
    """What the figures report: per input, the RMS error against the clean lengths (pps,
    BRA/TRImed arrays) as (name, Ia unfiltered, II unfiltered, Ia filtered, II filtered); the
    PI predictor's step overshoot (fraction of the step) and ramp overshoot (L0)."""

    noise_rows: list[tuple]
    step_overshoot: float
    ramp_overshoot_L0: float

    def report(self) -> str:
        lines = ["RMS error vs clean lengths (pps), BRA / TRImed:",
                 f"{'input':30s} {'Ia unfiltered':>16s} {'II unfiltered':>16s} "
                 f"{'Ia filtered':>14s} {'II filtered':>14s}"]
        for name, *vals in self.noise_rows:
            lines.append(f"{name:30s} " + " ".join(f"{v[0]:7.2f}/{v[1]:<7.2f}" for v in vals))
        lines.append(f"PI predictor: step overshoot {100 * self.step_overshoot:.0f} % of the "
                     f"step; ramp (0.5 L0/s) overshoots its stop by "
                     f"{self.ramp_overshoot_L0:.4f} L0")
        return "\n".join(lines)


def run(out_dir: Path, quick: bool = False, duration_s: float = 3.0) -> ChainFigureNumbers:
    """Write ``derivative_noise.png`` and ``predictor_overshoot.png`` into ``out_dir``
    (``quick`` changes nothing: both take seconds)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    noise = noise_experiment(duration_s)
    plot_noise(noise, out_dir / "derivative_noise.png")
    pred = predictor_experiment()
    plot_predictor(pred, out_dir / "predictor_overshoot.png")
    t = pred["t"]
    step_os = (pred["template"][(t > 0.3) & (t < 1.5)].max() - 1.05) / 0.1
    ramp_os = (0.9 - pred["template"][t > 1.8].min())
    return ChainFigureNumbers(noise["rows"], float(step_os), float(ramp_os))
