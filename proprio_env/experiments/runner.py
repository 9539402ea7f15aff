"""Run every validation experiment into one folder: figures, tables and a summary.

Each :class:`Step` writes into its own sub-folder of the output and returns a short markdown
summary; :func:`run_steps` runs them in order with a progress bar, sends what a step prints
to ``logs/<step>.log`` (so the bar stays readable) and writes ``summary.md``.
``scripts/validate.py`` is the command line; it adds the steps that live in ``scripts/``
(spindle accuracy, length fits, demo).
"""

from __future__ import annotations

import contextlib
import csv
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from proprio_env.validation import ecrb, human_gains

HUMAN_LIMIT_PPS = human_gains.HUMAN_LIMIT_PPS
PNG_COLOURS = 128


@dataclass(frozen=True)
class Step:
    """One experiment: ``run(out_dir, quick)`` writes its files into ``out_dir`` and returns
    a markdown summary (a few lines)."""

    name: str
    title: str
    run: Callable[[Path, bool], str]


def shrink_png(path: Path, colours: int = PNG_COLOURS) -> int:
    """Re-save a figure as a palette PNG (plots use few colours): 3-5x smaller. Returns the new
    size in bytes; a file Pillow cannot read is left as it is."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow comes with matplotlib
        return path.stat().st_size
    with Image.open(path) as im:
        small = im.convert("RGB").quantize(colours, method=Image.Quantize.MEDIANCUT)
    small.save(path, optimize=True)
    return path.stat().st_size


def human_gains_step(out_dir: Path, quick: bool) -> str:
    result = human_gains.run_human_gains(duration_s=1.5 if quick else 6.0,
                                         angle_step_deg=5.0 if quick else 1.0)
    table = human_gains.markdown_table(result)
    (out_dir / "human_gains.md").write_text(table)
    human_gains.write_csv(result, out_dir / "human_gains.csv")
    human_gains.plot(result, out_dir / "human_gains.png")
    static = result.worst("HUMAN", "static")
    motion = result.worst("HUMAN", "motion")
    ratio = result.worst("CAT", "static") / static
    return (
        f"- largest fusimotor swing, HUMAN, static over 0-130 deg: **{static:.1f} pps** "
        f"({'below' if static < HUMAN_LIMIT_PPS else 'ABOVE'} the paper's 30 pps)\n"
        f"- largest fusimotor swing, HUMAN, during the demo motion: **{motion:.1f} pps** "
        f"({'below' if motion < HUMAN_LIMIT_PPS else 'above'} 30 pps)\n"
        f"- CAT / HUMAN: {ratio:.2f}\n\n{table}"
    )


def ecrb_step(out_dir: Path, quick: bool) -> str:
    # quick: the fast ramp and the fast sinusoid only
    runs = ecrb.run_ecrb(ecrb.PROTOCOLS[1::2] if quick else ecrb.PROTOCOLS)
    curve = ecrb.EcrbCurve.load()
    reference = None
    if ecrb.SHARED_REFERENCE.is_file():
        reference = ecrb.read_table(ecrb.SHARED_REFERENCE)
    table = ecrb.markdown_table(runs)
    (out_dir / "ecrb_ranges.md").write_text(table)
    ecrb.plot(runs, out_dir / "ecrb_protocol.png")
    ecrb.plot_curve(curve, out_dir / "ecrb_length.png", reference)
    if reference is None:
        check = "OpenSim reference not found (../shared absent): curve not re-checked"
    else:
        diff = ecrb.compare_with_reference(curve, reference)
        check = f"largest difference from the OpenSim reference: {diff:.1e} L0"
    return f"- ECRB curve: {check}\n\n{table}"


def obstruction_step(out_dir: Path, quick: bool) -> str:
    from proprio_env.obstruction import run_obstruction

    metrics = run_obstruction(out_dir, quick=quick)
    with (out_dir / "obstruction_metrics.csv").open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["measure", "value"])
        for k, v in metrics.items():
            w.writerow([k, f"{v:.4f}"])
    lines = ["| template from | baseline | BRA II RMS (pps) | TRImed II RMS (pps) |",
             "|---|---|---:|---:|"]
    for source in ("measured", "intended"):
        for base in ("voluntary stop", "unobstructed"):
            lines.append(f"| {source} motion | {base} | "
                         f"{metrics[f'{source}/{base}/BRA_ii_rms_pps']:.1f} | "
                         f"{metrics[f'{source}/{base}/TRImed_ii_rms_pps']:.1f} |")
    table = "\n".join(lines) + "\n"
    (out_dir / "obstruction.md").write_text(table)
    return (f"- forearm stopped at {metrics['max_angle_deg']:.2f} deg (obstacle 70 deg, "
            f"overshoot {metrics['overshoot_deg']:.2f} deg), contact at "
            f"{metrics['contact_s']:.2f} s\n"
            "- II RMS difference of the obstructed run while blocked:\n\n" + table)


PACKAGE_STEPS = (
    Step("human_gains", "Human gains: fusimotor swing with HUMAN and CAT", human_gains_step),
    Step("ecrb", "Human ECRB wrist protocol (Fig. 6)", ecrb_step),
    Step("obstruction", "Obstructed movement (Fig. 7)", obstruction_step),
)


def run_steps(steps: Sequence[Step], out_dir: Path, quick: bool = False,
              progress: bool = True) -> dict[str, str]:
    """Run ``steps`` into ``out_dir/<step.name>``; write ``summary.md``; return the summaries.

    A step that raises stops the run (the error names the step; its log is kept)."""
    from tqdm import tqdm

    out_dir = Path(out_dir)
    (out_dir / "logs").mkdir(parents=True, exist_ok=True)
    summaries: dict[str, str] = {}
    seconds: dict[str, float] = {}
    bar = tqdm(steps, desc="validation", unit="step", disable=not progress)
    for step in bar:
        bar.set_postfix_str(step.name)
        step_dir = out_dir / step.name
        step_dir.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        log = out_dir / "logs" / f"{step.name}.log"
        with log.open("w") as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
            try:
                summaries[step.name] = step.run(step_dir, quick)
            except Exception as exc:
                raise RuntimeError(f"validation step {step.name!r} failed ({exc!r}); "
                                   f"see {log}") from exc
        for png in step_dir.glob("*.png"):
            shrink_png(png)
        seconds[step.name] = time.perf_counter() - start
    mode = "quick (reduced)" if quick else "full"
    parts = [f"# Validation summary ({mode} run)\n"]
    for step in steps:
        files = ", ".join(sorted(p.name for p in (out_dir / step.name).iterdir()))
        parts.append(f"## {step.title}\n\n{summaries[step.name].rstrip()}\n\n"
                     f"files in `{step.name}/`: {files} ({seconds[step.name]:.1f} s)\n")
    (out_dir / "summary.md").write_text("\n".join(parts))
    return summaries
