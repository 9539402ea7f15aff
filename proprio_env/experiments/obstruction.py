"""Obstructed movement (the seed paper's Fig. 7, after Prochazka et al.): can the afferents
tell an unexpected stop from an intended one?

The servo-driven MuJoCo elbow flexes from ``start_deg`` towards ``target_deg`` at
``speed_deg_s``. Three runs:

- *unobstructed*: the movement as intended;
- *obstructed*: the same intended movement, stopped part-way by an obstacle at
  ``obstacle_deg`` (:func:`proprio_env.body.model.load_model`);
- *voluntary stop*: a movement intended to stop where the obstacle stopped the forearm.

The chain (CAT gains, as the paper uses for its cat data) runs on each measured motion with
the fusimotor template taken (a) from the measured motion or (b) from the intended motion
(the chain's switch, :meth:`spindle.chain.ArmChain.set_intended_angle`).

The measure of an "afferent signature of the unexpected stop": during the blocked interval
(from the first contact to the end of the run; and the "held" part of it, from
``SETTLE_S`` after contact, when the stop's transient is over) the RMS difference, in pps,
between the obstructed run and the voluntary stop, which share almost the same measured motion and
differ only in what was intended. With (a) the chain cannot see the difference (the template
comes from the motion alone); with (b) it can. The deviation from the unobstructed run (the
naive measure, which mixes in the different muscle lengths) is reported too.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import spindle
from proprio_env.body.model import load_model
from proprio_env.body.servo_motion import ServoMotion, drive_servo
from spindle.chain import MUSCLES, ChainConfig, ChainTrace, run_chain

CONTACT_TOLERANCE_DEG = 0.5
"""The forearm counts as blocked once it is this close to the obstacle angle."""
SETTLE_S = 0.3
"""The "held" window starts this long after contact, when the stop's transient is over."""


@dataclass(frozen=True)
class ObstructionSetup:
    """The protocol (angles in deg, times in s)."""

    start_deg: float = 30.0
    target_deg: float = 110.0
    obstacle_deg: float = 70.0
    speed_deg_s: float = 130.0
    onset_s: float = 0.3
    duration_s: float = 2.0
    sample_rate_hz: float = 500.0
    params: spindle.SpindleParams = spindle.CAT

    def command_deg(self, t_s: np.ndarray, stop_deg: float | None = None) -> np.ndarray:
        """The servo command: rest, a constant-speed ramp, hold at the target (or stop_deg)."""
        end = self.target_deg if stop_deg is None else stop_deg
        return np.clip(self.start_deg + self.speed_deg_s * (t_s - self.onset_s),
                       self.start_deg, end)


@dataclass(frozen=True)
class ObstructionResult:
    setup: ObstructionSetup
    t_s: np.ndarray
    blocked: np.ndarray
    motions: dict[str, ServoMotion]
    intended_deg: dict[str, np.ndarray]
    traces: dict[tuple[str, str], ChainTrace]
    metrics: dict[str, float]


def _resample(motion: ServoMotion, t_s: np.ndarray) -> np.ndarray:
    return np.interp(t_s, motion.t_s, motion.angle_deg)


def run_experiment(setup: ObstructionSetup | None = None) -> ObstructionResult:
    """Run the three movements and both template sources; compute the measures."""
    setup = ObstructionSetup() if setup is None else setup
    free_model = load_model()
    blocked_model = load_model(obstacle_deg=setup.obstacle_deg)
    t_phys = np.arange(0.0, setup.duration_s, free_model.opt.timestep)
    motions = {
        "unobstructed": drive_servo(setup.command_deg(t_phys), free_model),
        "obstructed": drive_servo(setup.command_deg(t_phys), blocked_model),
    }
    stop_deg = float(motions["obstructed"].angle_deg[-1])
    # The servo holds a little below its command under gravity: aim the voluntary stop so
    # that the forearm rests where the obstacle held it (one correction suffices: the error
    # is nearly constant).
    command_stop = stop_deg
    for _ in range(2):
        voluntary = drive_servo(setup.command_deg(t_phys, command_stop), free_model)
        command_stop += stop_deg - float(voluntary.angle_deg[-1])
    motions["voluntary stop"] = voluntary
    t = np.arange(0.0, t_phys[-1], 1.0 / setup.sample_rate_hz)
    intended = {
        "unobstructed": setup.command_deg(t),
        "obstructed": setup.command_deg(t),
        "voluntary stop": setup.command_deg(t, stop_deg),  # intended: to stop there
    }
    config = ChainConfig(params=setup.params)
    traces = {}
    for run, motion in motions.items():
        angle = _resample(motion, t)
        traces[run, "measured"] = run_chain(t, angle_deg=angle, config=config)
        traces[run, "intended"] = run_chain(t, angle_deg=angle, config=config,
                                            intended_angle_deg=intended[run])
    obstructed_angle = _resample(motions["obstructed"], t)
    contact = np.flatnonzero(obstructed_angle >= setup.obstacle_deg - CONTACT_TOLERANCE_DEG)
    if contact.size == 0:
        raise RuntimeError("the forearm never reached the obstacle; check the setup")
    blocked = t >= t[contact[0]]
    held = t >= t[contact[0]] + SETTLE_S
    metrics: dict[str, float] = {
        "contact_s": float(t[contact[0]]),
        "max_angle_deg": float(motions["obstructed"].angle_deg.max()),
        "overshoot_deg": float(motions["obstructed"].angle_deg.max() - setup.obstacle_deg),
    }
    for source in ("measured", "intended"):
        obs = traces["obstructed", source]
        for baseline in ("voluntary stop", "unobstructed"):
            base = traces[baseline, source]
            for field in ("ii_pps", "ia_pps"):
                for window, mask in (("", blocked), ("held ", held)):
                    diff = getattr(obs, field)[mask] - getattr(base, field)[mask]
                    for k, muscle in enumerate(MUSCLES):
                        key = f"{window}{source}/{baseline}/{muscle}_{field[:2]}_rms_pps"
                        metrics[key] = float(np.sqrt(np.mean(diff[:, k] ** 2)))
    return ObstructionResult(setup, t, blocked, motions, intended, traces, metrics)


def plot(result: ObstructionResult, out_dir: Path) -> list[Path]:
    """One figure per template source: angle, BRA/TRImed template and II for the three runs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    t = result.t_s
    styles = {"unobstructed": ("0.6", "-"), "voluntary stop": ("tab:blue", "--"),
              "obstructed": ("tab:red", "-")}
    for source in ("measured", "intended"):
        fig, axes = plt.subplots(5, 1, figsize=(8, 11), sharex=True)
        for run, (color, ls) in styles.items():
            trace = result.traces[run, source]
            axes[0].plot(t, trace.angle_deg, color=color, ls=ls, label=run)
            for k in range(2):
                axes[1 + k].plot(t, trace.ii_pps[:, k], color=color, ls=ls)
            axes[3].plot(t, trace.gamma_static_pps[:, 0], color=color, ls=ls)
            axes[4].plot(t, trace.gamma_dynamic_pps[:, 0], color=color, ls=ls,
                         drawstyle="steps-post")
        axes[0].axhline(result.setup.obstacle_deg, color="k", lw=0.6, ls=":")
        axes[0].set_ylabel("elbow angle (deg)")
        axes[0].legend(fontsize=8)
        axes[1].set_ylabel("BRA II (pps)")
        axes[2].set_ylabel("TRImed II (pps)")
        axes[3].set_ylabel("BRA γs (pps)")
        axes[4].set_ylabel("BRA γd (pps)")
        axes[4].set_xlabel("time (s)")
        for ax in axes:
            ax.axvspan(t[result.blocked][0], t[-1], color="0.9", zorder=-1)
        m = result.metrics
        axes[0].set_title(
            f"Fusimotor template from the {source} motion (CAT gains): obstructed vs voluntary "
            f"stop, BRA II RMS {m[f'{source}/voluntary stop/BRA_ii_rms_pps']:.1f} pps while "
            "blocked", fontsize=9)
        fig.tight_layout()
        path = out_dir / f"obstruction_{source}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        paths.append(path)
    return paths


def metrics_table_md(metrics: dict[str, float]) -> str:
    """II RMS difference of the obstructed run while blocked, per template source and
    baseline (markdown)."""
    lines = ["| template from | baseline | BRA II RMS (pps) | TRImed II RMS (pps) |",
             "|---|---|---:|---:|"]
    for source in ("measured", "intended"):
        for base in ("voluntary stop", "unobstructed"):
            lines.append(f"| {source} motion | {base} | "
                         f"{metrics[f'{source}/{base}/BRA_ii_rms_pps']:.1f} | "
                         f"{metrics[f'{source}/{base}/TRImed_ii_rms_pps']:.1f} |")
    return "\n".join(lines) + "\n"


def write_metrics_csv(metrics: dict[str, float], path: Path) -> Path:
    with path.open("w", newline="") as f:
        w = csv.writer(f, lineterminator="\n")
        w.writerow(["measure", "value"])
        for k, v in metrics.items():
            w.writerow([k, f"{v:.4f}"])
    return path


@dataclass(frozen=True)
class ObstructionNumbers:
    """What the experiment reports: every measure of :func:`run_experiment` and the table of
    the II RMS differences (markdown)."""

    metrics: dict[str, float]
    table_md: str

    def summary_md(self) -> str:
        m = self.metrics
        return (f"- forearm stopped at {m['max_angle_deg']:.2f} deg (obstacle 70 deg, "
                f"overshoot {m['overshoot_deg']:.2f} deg), contact at "
                f"{m['contact_s']:.2f} s\n"
                "- II RMS difference of the obstructed run while blocked:\n\n" + self.table_md)


def run(out_dir: Path, quick: bool = False) -> ObstructionNumbers:
    """Write ``obstruction_{measured,intended}.png``, ``obstruction_metrics.csv`` and
    ``obstruction.md`` into ``out_dir`` (``quick`` shortens the hold after the stop)."""
    out_dir = Path(out_dir)
    result = run_experiment(ObstructionSetup(duration_s=1.4 if quick else 2.0))
    out_dir.mkdir(parents=True, exist_ok=True)
    plot(result, out_dir)
    write_metrics_csv(result.metrics, out_dir / "obstruction_metrics.csv")
    table = metrics_table_md(result.metrics)
    (out_dir / "obstruction.md").write_text(table)
    return ObstructionNumbers(result.metrics, table)
