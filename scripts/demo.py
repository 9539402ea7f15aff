"""Demo of the chain built so far: elbow angle -> fitted fibre lengths -> human spindles.

Drives the elbow through repeated rapid flexion-extension (~130 deg/s, as in the seed paper's
Fig. 8), turns the angle into brachialis (BRA) and triceps-medial (TRImed) normalised fibre
lengths with the fits in ``models/length_fits.json``, and runs the HUMAN spindle preset at
constant fusimotor drive. Writes a figure and a CSV of every signal into ``--out`` and prints a
summary. The encoder stage and the fusimotor model join this chain in later releases.

    python scripts/demo.py [--out DIR] [--duration S]
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np

import spindle

SPEED_DEG_S = 130.0
RANGE_DEG = (20.0, 110.0)


def elbow_angle_deg(t_s: np.ndarray) -> np.ndarray:
    """Triangle wave between RANGE_DEG at SPEED_DEG_S, corners rounded over 50 ms."""
    lo, hi = RANGE_DEG
    period = 2 * (hi - lo) / SPEED_DEG_S
    phase = (t_s % period) / period
    tri = lo + (hi - lo) * (1 - np.abs(2 * phase - 1))
    # round the corners: real joints cannot reverse instantly (a 50 ms moving average)
    k = max(1, int(0.05 / (t_s[1] - t_s[0])))
    padded = np.pad(tri, (k, k), mode="edge")
    return np.convolve(padded, np.ones(k) / k, mode="same")[k:-k]


def run(duration_s: float, dt_s: float = 1e-3) -> dict[str, np.ndarray]:
    t = np.arange(0, duration_s, dt_s)
    angle_deg = elbow_angle_deg(t)
    fits = spindle.load_length_fits()
    lengths = fits.length_L0(np.deg2rad(angle_deg))  # (T, 2): BRA, TRImed
    result = spindle.simulate(lengths, dt_s, gamma_dyn=70.0, gamma_stat=70.0,
                              params=spindle.HUMAN)
    out = {"t_s": t, "elbow_deg": angle_deg}
    for k, muscle in enumerate(fits.muscles):
        out[f"{muscle}_length_L0"] = lengths[:, k]
        out[f"{muscle}_ia_pps"] = result.ia[:, k]
        out[f"{muscle}_ii_pps"] = result.ii[:, k]
    return out


def write_csv(signals: dict[str, np.ndarray], path: Path) -> None:
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(signals)
        writer.writerows(zip(*signals.values(), strict=True))


def plot(signals: dict[str, np.ndarray], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    muscles = [k.removesuffix("_length_L0") for k in signals if k.endswith("_length_L0")]
    fig, axes = plt.subplots(4, len(muscles), figsize=(11, 8), sharex=True)
    t = signals["t_s"]
    for col, m in enumerate(muscles):
        axes[0, col].plot(t, signals["elbow_deg"], "k")
        axes[0, col].set_ylabel("elbow flexion (deg)")
        axes[0, col].set_title(m)
        axes[1, col].plot(t, signals[f"{m}_length_L0"])
        axes[1, col].set_ylabel("fibre length (L0)")
        axes[2, col].plot(t, signals[f"{m}_ia_pps"], "C3")
        axes[2, col].set_ylabel("Ia (pps)")
        axes[3, col].plot(t, signals[f"{m}_ii_pps"], "C2")
        axes[3, col].set_ylabel("II (pps)")
        axes[3, col].set_xlabel("time (s)")
    fig.suptitle("Elbow flexion-extension at ~130 deg/s -> human spindle afferents "
                 "(gamma_dyn = gamma_stat = 70 pps)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/demo"))
    parser.add_argument("--duration", type=float, default=6.0, help="seconds of motion")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    signals = run(args.duration)
    elapsed = time.perf_counter() - start
    write_csv(signals, args.out / "demo_signals.csv")
    plot(signals, args.out / "demo.png")
    for key, values in signals.items():
        if not np.isfinite(values).all():
            raise SystemExit(f"non-finite values in {key}")
    print(f"simulated {args.duration:g} s of elbow motion in {elapsed:.2f} s")
    for m in ("BRA", "TRImed"):
        ia, ii = signals[f"{m}_ia_pps"], signals[f"{m}_ii_pps"]
        lengths = signals[f"{m}_length_L0"]
        print(f"{m:7s} length {lengths.min():.3f}-{lengths.max():.3f} L0   "
              f"Ia {ia.min():6.1f}-{ia.max():6.1f} pps   II {ii.min():6.1f}-{ii.max():6.1f} pps")
    print(f"wrote {args.out / 'demo.png'} and {args.out / 'demo_signals.csv'}")


if __name__ == "__main__":
    main()
