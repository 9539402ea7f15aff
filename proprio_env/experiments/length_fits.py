"""The reduced length model ``models/length_fits.json`` and its figure (the seed paper's Fig. 5).

Command line: ``python scripts/fit_lengths.py`` (rewrites ``models/length_fits.json``).

Sweeps the MJCF elbow (``models/elbow.xml``) over 0-130 deg, fits each muscle's normalised
fibre length with a Chebyshev series whose degree is chosen by held-out error, records the
coefficients, valid range, max error and the sha256 of ``elbow.xml``, and draws the curves
like the seed paper's Fig. 5 with the OpenSim oracle (``tests/data/arm26_elbow_oracle.csv``)
overlaid. The fit target is 0.001 L0.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from proprio_env.body.length_fitting import (
    DEFAULT_MAX_DEGREE,
    DEFAULT_STEP_DEG,
    DEFAULT_TOLERANCE_L0,
    TARGET_L0,
    default_output,
    fit_document,
    write_fits,
)
from proprio_env.body.model import load_model, model_path
from spindle.chain.length_model import load_length_fits

REPO_ROOT = Path(__file__).resolve().parents[2]
# A source checkout's oracle; absent from an installed wheel, where the figure goes without it.
DEFAULT_ORACLE = REPO_ROOT / "tests" / "data" / "arm26_elbow_oracle.csv"


def read_oracle(path: Path) -> dict[str, np.ndarray] | None:
    """FibreColumns of the OpenSim oracle CSV ('#' comment lines first), or None if absent."""
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


@dataclass(frozen=True)
class LengthFitNumbers:
    """What the experiment reports: where the fits went, the sha256 of the MJCF they fit, and
    per muscle its fit entry (``degree``, ``max_error_L0``, ``heldout_max_error_L0``, ...)."""

    fits_file: Path
    model_sha256: str
    muscles: dict[str, dict]

    @property
    def within_target(self) -> bool:
        return all(e["max_error_L0"] <= TARGET_L0 for e in self.muscles.values())

    def summary_md(self) -> str:
        rows = [f"- {m}: Chebyshev degree {e['degree']}, max error {e['max_error_L0']:.1e} L0 "
                f"against the exact MuJoCo lengths" for m, e in self.muscles.items()]
        return "\n".join(rows) + "\n"


def fit_and_draw(model_file: Path | None = None, fits_file: Path | None = None,
                 figure: Path | None = None, oracle: Path = DEFAULT_ORACLE,
                 step_deg: float = DEFAULT_STEP_DEG, tolerance_L0: float = DEFAULT_TOLERANCE_L0,
                 max_degree: int = DEFAULT_MAX_DEGREE) -> LengthFitNumbers:
    """Sweep and fit ``model_file`` (default ``models/elbow.xml``), write the fits to
    ``fits_file`` (default: next to the model) and, if ``figure`` is given, draw it there."""
    model_file = (model_file or model_path()).resolve()
    fits_file = fits_file or default_output(model_file)
    doc, exact = fit_document(load_model(model_file), model_file, step_deg, tolerance_L0,
                              max_degree)
    write_fits(doc, fits_file)
    fits = load_length_fits(fits_file, model_xml=model_file)
    if figure is not None:
        draw(figure, exact, fits, read_oracle(oracle))
    return LengthFitNumbers(Path(fits_file), doc["model_sha256"], doc["muscles"])


def run(out_dir: Path, quick: bool = False) -> LengthFitNumbers:
    """Fit the bundled elbow into ``out_dir/length_fits.json`` (the committed
    ``models/length_fits.json`` is left alone) and draw ``length_fits.png``; raise if a fit
    misses the 0.001 L0 target. ``quick`` changes nothing: the sweep takes seconds."""
    out_dir = Path(out_dir)
    numbers = fit_and_draw(fits_file=out_dir / "length_fits.json",
                           figure=out_dir / "length_fits.png")
    if not numbers.within_target:
        raise ValueError(f"a length fit misses the {TARGET_L0} L0 target: {numbers.muscles}")
    return numbers
