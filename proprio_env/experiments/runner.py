"""Run every validation experiment into one folder: figures, tables and a summary.

Each :class:`Step` writes into its own sub-folder of the output and returns its numbers with
a short markdown summary; :func:`run_steps` runs them in order with a progress bar, sends
what a step prints to ``logs/<step>.log`` (so the bar stays readable) and writes
``summary.md``. ``scripts/validate.py`` is the command line over
:func:`validation_steps`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Protocol

from proprio_env.experiments import (
    demo,
    ecrb,
    human_gains,
    length_fits,
    obstruction,
    spindle_accuracy,
    stimulation,
)

PNG_COLOURS = 128


class Numbers(Protocol):
    """What an experiment's ``run`` returns: its numbers, able to summarise themselves."""

    def summary_md(self) -> str: ...


@dataclass(frozen=True)
class Step:
    """One experiment: ``run(out_dir, quick)`` writes its files into ``out_dir`` and returns
    its numbers (:class:`Numbers`)."""

    name: str
    title: str
    run: Callable[[Path, bool], Numbers]


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


def validation_steps(jobs: int = 1) -> tuple[Step, ...]:
    """Every experiment of ``scripts/validate.py``, in its order (``jobs``: worker processes
    of the spindle accuracy sweep)."""
    return (
        Step("human_gains", "Human gains: fusimotor swing with HUMAN and CAT", human_gains.run),
        Step("ecrb", "Human ECRB wrist protocol (Fig. 6)", ecrb.run),
        Step("obstruction", "Obstructed movement (Fig. 7)", obstruction.run),
        Step("spindle_accuracy", "Spindle accuracy on the Mileusnic Fig. 3 protocol",
             partial(spindle_accuracy.run, jobs=jobs)),
        Step("length_fits", "Length fits (the paper's Fig. 5)", length_fits.run),
        Step("demo", "Chain demo (the paper's Fig. 8)", demo.run),
        Step("stimulation", "Stimulator stage on the demo motion", stimulation.run),
    )


def run_steps(steps: Sequence[Step], out_dir: Path, quick: bool = False,
              progress: bool = True) -> dict[str, Numbers]:
    """Run ``steps`` into ``out_dir/<step.name>``; write ``summary.md``; return each step's
    numbers.

    A step that raises stops the run (the error names the step; its log is kept)."""
    from tqdm import tqdm

    out_dir = Path(out_dir)
    (out_dir / "logs").mkdir(parents=True, exist_ok=True)
    numbers: dict[str, Numbers] = {}
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
                numbers[step.name] = step.run(step_dir, quick)
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
        parts.append(f"## {step.title}\n\n{numbers[step.name].summary_md().rstrip()}\n\n"
                     f"files in `{step.name}/`: {files} ({seconds[step.name]:.1f} s)\n")
    (out_dir / "summary.md").write_text("\n".join(parts))
    return numbers
