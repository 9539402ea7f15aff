"""Regenerate the reduced length model ``models/length_fits.json`` and its figure.

    python scripts/fit_lengths.py                      # writes models/length_fits.json
    python scripts/fit_lengths.py --out out/fig5.png   # figure path (default out/length_fits.png)

Sweeps the MJCF elbow (``models/elbow.xml``) over 0-130 deg, fits each muscle's normalised
fibre length with a Chebyshev series whose degree is chosen by held-out error, records the
coefficients, valid range, max error and the sha256 of ``elbow.xml``, and draws the curves
like the seed paper's Fig. 5 with the OpenSim oracle (``tests/data/arm26_elbow_oracle.csv``)
overlaid. Exits non-zero if a fit misses the 0.001 L0 target.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from proprio_env.length_fitting import (
    DEFAULT_MAX_DEGREE,
    DEFAULT_STEP_DEG,
    DEFAULT_TOLERANCE_L0,
    TARGET_L0,
    default_output,
    fit_document,
    write_fits,
)
from proprio_env.model import load_model, model_path
from spindle.length_fits import load_length_fits

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ORACLE = REPO_ROOT / "tests" / "data" / "arm26_elbow_oracle.csv"
DEFAULT_FIGURE = REPO_ROOT / "out" / "length_fits.png"


def read_oracle(path: Path) -> dict[str, np.ndarray] | None:
    """Columns of the OpenSim oracle CSV ('#' comment lines first), or None if absent."""
    if not path.is_file():
        return None
    lines = [ln for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    names = lines[0].split(",")
    table = np.array([[float(v) for v in ln.split(",")] for ln in lines[1:]])
    return {n: table[:, i] for i, n in enumerate(names)}


def draw(figure: Path, exact, fits, oracle: dict[str, np.ndarray] | None) -> None:
    """Fig. 5 of the seed paper (normalised fibre length vs elbow angle) plus error panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    deg = np.degrees(exact.angle_rad)
    colours = {"BRA": "tab:red", "TRImed": "tab:blue"}
    fig, (ax, ax_err) = plt.subplots(
        2, 1, figsize=(6.4, 6.4), sharex=True, gridspec_kw={"height_ratios": [2.2, 1]}
    )
    fitted = fits.length_L0(exact.angle_rad)
    for j, name in enumerate(exact.muscles):
        c = colours.get(name)
        ax.plot(
            deg,
            exact.fibre_length_L0[:, j],
            color=c,
            lw=2.5,
            alpha=0.5,
            label=f"{name} MuJoCo (exact)",
        )
        ax.plot(
            deg,
            fitted[:, j],
            color=c,
            lw=1,
            ls="--",
            label=f"{name} fit, degree {fits[name].degree}",
        )
        ax_err.plot(
            deg,
            (fitted[:, j] - exact.fibre_length_L0[:, j]) * 1e3,
            color=c,
            lw=1,
            label=f"{name} fit - exact",
        )
        if oracle is not None:
            odeg = oracle["elbow_flex_deg"]
            ax.plot(
                odeg[::5],
                oracle[f"{name}_norm_fiber_length"][::5],
                "o",
                ms=4,
                mfc="none",
                color=c,
                label=f"{name} OpenSim (passive eq.)",
            )
            exact_at = np.interp(np.radians(odeg), exact.angle_rad, exact.fibre_length_L0[:, j])
            ax_err.plot(
                odeg,
                (exact_at - oracle[f"{name}_norm_fiber_length"]) * 1e3,
                ":",
                color=c,
                label=f"{name} exact - OpenSim passive eq.",
            )
    ax.set_ylabel("normalised fibre length (L0)")
    ax.set_title("Fibre length vs elbow flexion (cf. seed paper Fig. 5)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    ax_err.axhline(TARGET_L0 * 1e3, color="k", lw=0.5, ls="--", label="fit target")
    ax_err.axhline(-TARGET_L0 * 1e3, color="k", lw=0.5, ls="--")
    ax_err.set_xlabel("elbow flexion (deg)")
    ax_err.set_ylabel("error (10$^{-3}$ L0)")
    bottom, top = ax_err.get_ylim()
    ax_err.set_ylim(bottom, top + 0.6 * (top - bottom))  # room for the legend above the curves
    ax_err.legend(fontsize=7, ncol=2, loc="upper right")
    ax_err.grid(alpha=0.3)
    fig.tight_layout()
    figure.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(figure, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", type=Path, default=None, help="MJCF (default: models/elbow.xml)")
    p.add_argument(
        "--fits",
        type=Path,
        default=None,
        help="JSON to write (default: length_fits.json next to the model)",
    )
    p.add_argument("--out", type=Path, default=DEFAULT_FIGURE, help="figure (PNG) to write")
    p.add_argument("--no-figure", action="store_true", help="skip the figure")
    p.add_argument("--oracle", type=Path, default=DEFAULT_ORACLE, help="OpenSim oracle CSV")
    p.add_argument("--step-deg", type=float, default=DEFAULT_STEP_DEG, help="sweep step, deg")
    p.add_argument(
        "--tolerance",
        type=float,
        default=DEFAULT_TOLERANCE_L0,
        help="held-out max error (L0) a degree must reach",
    )
    p.add_argument("--max-degree", type=int, default=DEFAULT_MAX_DEGREE)
    args = p.parse_args(argv)

    model_file = (args.model or model_path()).resolve()
    fits_file = args.fits or default_output(model_file)
    model = load_model(model_file)
    doc, exact = fit_document(model, model_file, args.step_deg, args.tolerance, args.max_degree)
    write_fits(doc, fits_file)
    fits = load_length_fits(fits_file, model_xml=model_file)
    print(f"wrote {fits_file} (elbow.xml sha256 {doc['model_sha256'][:12]}...)")
    ok = True
    for name, entry in doc["muscles"].items():
        print(
            f"  {name}: degree {entry['degree']}, max error {entry['max_error_L0']:.2e} L0 "
            f"(held-out {entry['heldout_max_error_L0']:.2e} L0)"
        )
        ok &= entry["max_error_L0"] <= TARGET_L0
    if not args.no_figure:
        draw(args.out, exact, fits, read_oracle(args.oracle))
        print(f"wrote {args.out}")
    if not ok:
        print(f"a fit misses the {TARGET_L0} L0 target; raise --max-degree", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
