"""The whole chain on the bundled elbow: servo motion -> encoder -> ... -> Ia, II (the main job).

As in the seed paper's Fig. 8: the MuJoCo elbow's position servo drives repeated rapid
flexion-extension (~130 deg/s, 20-110 deg). A simulated AX-12 encoder reads the angle
(~500 Hz, 0.29 deg counts, noise, jitter, rare glitches) and the prosthesis chain
(``spindle.chain``: median filter, f(x), fitted lengths, low-pass, fusimotor template,
gamma_s/gamma_d, HUMAN spindles) turns the readings into Ia and II of the brachialis (BRA)
and the triceps medial head (TRImed).

Beside it, at the same sample times, two noise-free chains run on the motion MuJoCo really
made: one on the clean angle through the fitted lengths (reduced), one on MuJoCo's exact
tendon-derived fibre lengths (exact). The summary reports the exact-vs-reduced difference
(what the fitted length model costs) and the encoder-vs-clean difference (what the sensor
stage costs), in pps.

Writes ``demo.png`` (one column per muscle) and ``demo_signals.csv`` (every signal) into
``--out`` (default ``out/demo``).

    python scripts/demo.py [--out DIR] [--duration S] [--seed N]
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import spindle
from proprio_env.model import load_model
from proprio_env.servo_motion import drive_servo, triangle_deg
from spindle.chain import MUSCLES, ChainTrace, run_chain
from spindle.sensor import Encoder


def run(duration_s: float, seed: int) -> dict[str, object]:
    model = load_model()
    t_phys = np.arange(0.0, duration_s, model.opt.timestep)
    motion = drive_servo(triangle_deg(t_phys), model)

    encoder = Encoder(rng=seed)
    t_s, counts = encoder.record(motion.t_s, motion.angle_deg)
    true_angle = np.interp(t_s, motion.t_s, motion.angle_deg)
    exact_L = np.stack([np.interp(t_s, motion.t_s, motion.length_L0[:, k]) for k in range(2)],
                       axis=-1)
    prosthesis = run_chain(t_s, counts=counts)
    reduced = run_chain(t_s, angle_deg=true_angle)
    exact = run_chain(t_s, length_L0=exact_L)
    return {"t_s": t_s, "true_angle_deg": true_angle, "exact_length_L0": exact_L,
            "prosthesis": prosthesis, "reduced": reduced, "exact": exact}


def rms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean((a - b) ** 2, axis=0))


def write_csv(result: dict[str, object], path: Path) -> None:
    cols = {"t_s": result["t_s"], "true_angle_deg": result["true_angle_deg"]}
    cols.update({k: v for k, v in result["prosthesis"].columns().items() if k != "t_s"})
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
    cal = spindle.sensor.Calibration()
    raw_deg = np.where(pro.counts >= 0, cal.angle_deg(pro.counts), np.nan)
    rows = ["encoder", "length", "gamma_s", "gamma_d", "ia", "ii"]
    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 12), sharex=True)
    for k, muscle in enumerate(MUSCLES):
        ax = axes[0, k]
        ax.plot(t, raw_deg, ".", ms=1.5, color="0.6", label="encoder raw")
        ax.plot(t, pro.angle_deg, lw=1, label="median filtered, f(x)")
        ax.plot(t, result["true_angle_deg"], lw=0.8, ls="--", color="k", label="MuJoCo")
        ax.set_ylim(0, 130)
        ax.set_ylabel("elbow angle (deg)")
        ax.set_title(f"{muscle}")
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
        axes[-1, k].set_xlabel("time (s)")
    for row in (0, 1, 4):
        axes[row, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle("Seed paper Fig. 8 protocol: servo-driven flexion-extension at ~130°/s, "
                 "HUMAN spindles")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    parser.add_argument("--duration", type=float, default=6.0, help="seconds of motion")
    parser.add_argument("--seed", type=int, default=0, help="encoder noise seed")
    args = parser.parse_args(argv)
    if not args.duration > 0:
        parser.error(f"--duration={args.duration} must be > 0")
    args.out.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    result = run(args.duration, args.seed)
    elapsed = time.perf_counter() - start
    write_csv(result, args.out / "demo_signals.csv")
    plot(result, args.out / "demo.png")

    pro, red, ex = result["prosthesis"], result["reduced"], result["exact"]
    print(f"{args.duration:g} s of servo motion, {pro.t_s.size} encoder samples "
          f"({pro.t_s.size / args.duration:.0f} Hz), chains run in {elapsed:.1f} s")
    print("encoder handling:", {k: v for k, v in pro.counters.items() if v})
    for k, muscle in enumerate(MUSCLES):
        print(f"{muscle:7s} Ia {pro.ia_pps[:, k].min():5.1f}-{pro.ia_pps[:, k].max():5.1f} pps,"
              f" II {pro.ii_pps[:, k].min():5.1f}-{pro.ii_pps[:, k].max():5.1f} pps | "
              f"exact vs reduced RMS Ia {rms(ex.ia_pps, red.ia_pps)[k]:.3f}, "
              f"II {rms(ex.ii_pps, red.ii_pps)[k]:.3f} pps | "
              f"encoder vs clean RMS Ia {rms(pro.ia_pps, red.ia_pps)[k]:.2f}, "
              f"II {rms(pro.ii_pps, red.ii_pps)[k]:.2f} pps")
    print(f"wrote {args.out / 'demo.png'} and {args.out / 'demo_signals.csv'}")


if __name__ == "__main__":
    main()
