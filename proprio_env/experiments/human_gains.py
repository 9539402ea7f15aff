"""Human gains: how far can fusimotor drive move Ia and II (the reason for G x 1/5)?

The seed paper scales every afferent gain G of Mileusnic's cat spindle by 1/5 because
fusimotor drive changes human spindle output by < 30 pps, against up to ~150 pps in the cat.
This experiment measures what the fusimotor model's drive does to our spindles, with the HUMAN
and the CAT preset, over the elbow's length range (static) and during the demo's motion.

Fusimotor settings: the model's range, gamma_s in {20, 36.25, ..., 150} pps (9 values) times
gamma_d in {0, 100} pps, each held constant; plus the undriven spindle (gamma_s = gamma_d = 0).

Measures, per muscle and afferent (pps), with r_k(t) the rate under setting k:

- ``swing``: max over time of [max_k r_k(t) - min_k r_k(t)] over the model's settings: the
  largest change the fusimotor model can make at one length (static) or one instant of the
  motion. This is the measure held to the paper's < 30 pps.
- ``vs_undriven``: max over time and settings of |r_k(t) - r_0(t)|: the change against a
  spindle with no fusimotor drive at all.
- ``model_driven`` (motion only): max over time of |r(t) - r_0(t)| where r(t) is driven by the
  chain's own fusimotor model (PI template, h(x), g(x)) during the demo motion.

Static rates are the spindle's equilibrium (:func:`spindle.core.equilibrium_state`), over the
elbow's 0-130 deg range in 1 deg steps through the fitted lengths. The motion is the demo's
(:func:`proprio_env.body.servo_motion.triangle_deg`: 20-110 deg at 130 deg/s, MuJoCo servo), its
angle sampled at 500 Hz through the chain's length model and low-pass.

All afferent rates of the Mileusnic model are positively homogeneous in the gains G (a sum of
clipped G-weighted stretches), so CAT/HUMAN is 5 by construction: the experiment confirms the
code keeps it so and shows where the HUMAN number lands.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

import spindle
from spindle import core
from spindle.chain import MUSCLES, run_chain
from spindle.chain.fusimotor import SEED_PAPER

PRESETS = {"HUMAN": spindle.HUMAN, "CAT": spindle.CAT}
HUMAN_LIMIT_PPS = 30.0
"""The seed paper's bound on the human fusimotor effect (its ref. [10])."""
AFFERENTS = ("ia", "ii")


def fusimotor_settings(n_static: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """(gamma_s, gamma_d) pairs in pps, shape (2 n_static,): the model's range, held constant."""
    gs = np.linspace(SEED_PAPER.gamma_static_min_pps, SEED_PAPER.gamma_static_max_pps, n_static)
    gd = np.array([0.0, SEED_PAPER.gamma_dynamic_pps])
    gs_grid, gd_grid = np.meshgrid(gs, gd, indexing="ij")
    return gs_grid.ravel(), gd_grid.ravel()


def static_rates(length_L0: np.ndarray, gamma_s_pps: np.ndarray, gamma_d_pps: np.ndarray,
                 params: spindle.SpindleParams) -> tuple[np.ndarray, np.ndarray]:
    """Equilibrium (Ia, II) in pps, shape (n_lengths, n_settings)."""
    L = np.asarray(length_L0, dtype=float)
    Lg, gs = np.meshgrid(L, gamma_s_pps, indexing="ij")
    _, gd = np.meshgrid(L, gamma_d_pps, indexing="ij")
    state = core.equilibrium_state(Lg.ravel(), gd.ravel(), gs.ravel(), params)
    ia, ii = core.afferents(state, params)
    return ia.reshape(Lg.shape), ii.reshape(Lg.shape)


@dataclass(frozen=True)
class GainResult:
    """Rates and measures. ``static`` / ``motion``: preset -> afferent -> array with settings on
    the last axis (static: (angles, muscles, settings); motion: (T, muscles, settings)); the
    undriven spindle is the last setting. ``driven``: preset -> afferent -> (T, muscles) under
    the chain's fusimotor model. ``table``: rows of (preset, condition, measure, muscle,
    afferent, pps)."""

    angle_deg: np.ndarray
    static: dict[str, dict[str, np.ndarray]]
    t_s: np.ndarray
    motion_angle_deg: np.ndarray
    motion: dict[str, dict[str, np.ndarray]]
    driven: dict[str, dict[str, np.ndarray]]
    table: list[tuple[str, str, str, str, str, float]]

    def value(self, preset: str, condition: str, measure: str, muscle: str,
              afferent: str) -> float:
        for row in self.table:
            if row[:5] == (preset, condition, measure, muscle, afferent):
                return row[5]
        raise KeyError((preset, condition, measure, muscle, afferent))

    def worst(self, preset: str, condition: str, measure: str = "swing") -> float:
        return max(r[5] for r in self.table if r[:3] == (preset, condition, measure))


def _measures(rates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(swing, vs_undriven) per muscle from (time, muscles, settings + undriven) rates."""
    model = rates[..., :-1]
    swing = (model.max(axis=-1) - model.min(axis=-1)).max(axis=0)
    vs_undriven = np.abs(model - rates[..., -1:]).max(axis=(0, 2))
    return swing, vs_undriven


def demo_motion(duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The demo's servo motion: (t_s, angle_deg) at 500 Hz."""
    from proprio_env.body.model import load_model
    from proprio_env.body.servo_motion import drive_servo, triangle_deg

    model = load_model()
    t_phys = np.arange(0.0, duration_s, model.opt.timestep)
    motion = drive_servo(triangle_deg(t_phys), model)
    t = np.arange(0.0, t_phys[-1], 1.0 / 500.0)
    return t, np.interp(t, motion.t_s, motion.angle_deg)


def run_human_gains(duration_s: float = 6.0, angle_step_deg: float = 1.0,
                    motion: tuple[np.ndarray, np.ndarray] | None = None) -> GainResult:
    """Static sweep and demo motion for HUMAN and CAT (``duration_s`` <= 0: static only)."""
    if not (np.isfinite(angle_step_deg) and angle_step_deg > 0):
        raise ValueError(f"angle_step_deg={angle_step_deg!r} must be finite and > 0")
    if not np.isfinite(duration_s):
        raise ValueError(f"duration_s={duration_s!r} must be finite")
    gs, gd = fusimotor_settings()
    gs_all, gd_all = np.append(gs, 0.0), np.append(gd, 0.0)
    fits = spindle.load_length_fits()
    lo, hi = np.degrees(fits.valid_range_rad)
    angle = np.arange(lo, hi + 1e-9, angle_step_deg)
    lengths = fits.length_L0(np.radians(angle))  # (angles, muscles)
    if motion is None and duration_s > 0:
        motion = demo_motion(duration_s)
    static: dict[str, dict[str, np.ndarray]] = {}
    moving: dict[str, dict[str, np.ndarray]] = {}
    driven: dict[str, dict[str, np.ndarray]] = {}
    table = []
    t = np.zeros(0) if motion is None else motion[0]
    motion_angle = np.zeros(0) if motion is None else motion[1]
    for name, params in PRESETS.items():
        per = [static_rates(lengths[:, k], gs_all, gd_all, params) for k in range(len(MUSCLES))]
        static[name] = {a: np.stack([p[j] for p in per], axis=1)
                        for j, a in enumerate(AFFERENTS)}
        if motion is not None:
            trace = run_chain(t, angle_deg=motion_angle)
            n_set = gs_all.size
            L = np.repeat(trace.length_L0, n_set, axis=1)  # (T, muscles * settings)
            v = np.repeat(trace.velocity_L0_s, n_set, axis=1)
            dt = float(t[1] - t[0])
            r = spindle.simulate(L, dt, velocity=v, gamma_dyn=np.tile(gd_all, len(MUSCLES)),
                                 gamma_stat=np.tile(gs_all, len(MUSCLES)), params=params)
            moving[name] = {"ia": r.ia.reshape(t.size, len(MUSCLES), n_set),
                            "ii": r.ii.reshape(t.size, len(MUSCLES), n_set)}
            d = spindle.simulate(trace.length_L0, dt, velocity=trace.velocity_L0_s,
                                 gamma_dyn=trace.gamma_dynamic_pps,
                                 gamma_stat=trace.gamma_static_pps, params=params)
            driven[name] = {"ia": d.ia, "ii": d.ii}
        for cond, rates in (("static", static[name]), ("motion", moving.get(name))):
            if rates is None:
                continue
            for a in AFFERENTS:
                swing, vs0 = _measures(rates[a])
                for k, muscle in enumerate(MUSCLES):
                    table.append((name, cond, "swing", muscle, a, float(swing[k])))
                    table.append((name, cond, "vs_undriven", muscle, a, float(vs0[k])))
                    if cond == "motion":
                        dev = np.abs(driven[name][a][:, k] - rates[a][:, k, -1]).max()
                        table.append((name, cond, "model_driven", muscle, a, float(dev)))
    return GainResult(angle, static, t, motion_angle, moving, driven, table)


def markdown_table(result: GainResult) -> str:
    """The measures as a markdown table (pps), HUMAN and CAT side by side with their ratio."""
    lines = ["| condition | measure | muscle | afferent | HUMAN (pps) | CAT (pps) | CAT/HUMAN |",
             "|---|---|---|---|---:|---:|---:|"]
    for row in result.table:
        if row[0] != "HUMAN":
            continue
        _, cond, measure, muscle, a, human = row
        cat = result.value("CAT", cond, measure, muscle, a)
        ratio = cat / human if human > 0 else float("nan")
        lines.append(f"| {cond} | {measure} | {muscle} | {a.upper()} | {human:.1f} | {cat:.1f} "
                     f"| {ratio:.2f} |")
    return "\n".join(lines) + "\n"


def plot(result: GainResult, path: Path) -> Path:
    """Static envelopes over the elbow angle and motion envelopes, HUMAN and CAT."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    has_motion = result.t_s.size > 0
    fig, axes = plt.subplots(2, 2 if has_motion else 1, figsize=(11 if has_motion else 6, 7),
                             squeeze=False)
    colors = {"BRA": "tab:blue", "TRImed": "tab:orange"}
    stride = max(1, result.t_s.size // 1500)
    for j, a in enumerate(AFFERENTS):
        ax = axes[j, 0]
        for k, muscle in enumerate(MUSCLES):
            for name, ls in (("HUMAN", "-"), ("CAT", ":")):  # CAT: 5 x HUMAN
                r = result.static[name][a][:, k, :-1]
                swing = r.max(axis=-1) - r.min(axis=-1)
                ax.plot(result.angle_deg, swing, color=colors[muscle], ls=ls,
                        label=f"{muscle} {name}")
        ax.axhline(HUMAN_LIMIT_PPS, color="k", lw=0.8, ls="--", label="30 pps (human)")
        ax.set_ylabel(f"{a.upper()} fusimotor swing (pps)")
        ax.set_xlabel("elbow angle (deg)")
        ax.set_title(f"static: max - min over γs 20-150, γd 0/100 ({a.upper()})", fontsize=9)
        ax.legend(fontsize=7, ncol=2)
        if has_motion:
            ax = axes[j, 1]
            for k, muscle in enumerate(MUSCLES):
                r = result.motion["HUMAN"][a][:, k, :-1]
                ax.fill_between(result.t_s[::stride], r.min(axis=-1)[::stride],
                                r.max(axis=-1)[::stride],
                                color=colors[muscle], alpha=0.3,
                                label=f"{muscle} HUMAN envelope")
                ax.plot(result.t_s[::stride], result.driven["HUMAN"][a][::stride, k],
                        color=colors[muscle],
                        lw=0.8, label=f"{muscle} fusimotor model")
            worst = max(result.value("HUMAN", "motion", "swing", m, a) for m in MUSCLES)
            ax.set_title(f"demo motion, HUMAN: range over the settings (largest swing "
                         f"{worst:.1f})", fontsize=9)
            ax.set_ylabel(f"{a.upper()} (pps)")
            ax.set_xlabel("time (s)")
            ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=70)
    plt.close(fig)
    return path


def write_csv(result: GainResult, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="\n") as f:
        f.write("preset,condition,measure,muscle,afferent,pps\n")
        for row in result.table:
            f.write(",".join(row[:5]) + f",{row[5]:.4f}\n")
    return path


@dataclass(frozen=True)
class HumanGainsNumbers:
    """What the experiment reports (pps): the largest HUMAN swing at rest and during the demo
    motion, CAT / HUMAN, and the full table (markdown)."""

    static_swing_pps: float
    motion_swing_pps: float
    cat_over_human: float
    table_md: str

    def summary_md(self) -> str:
        static, motion = self.static_swing_pps, self.motion_swing_pps
        return (
            f"- largest fusimotor swing, HUMAN, static over 0-130 deg: **{static:.1f} pps** "
            f"({'below' if static < HUMAN_LIMIT_PPS else 'ABOVE'} the paper's 30 pps)\n"
            f"- largest fusimotor swing, HUMAN, during the demo motion: **{motion:.1f} pps** "
            f"({'below' if motion < HUMAN_LIMIT_PPS else 'above'} 30 pps)\n"
            f"- CAT / HUMAN: {self.cat_over_human:.2f}\n\n{self.table_md}"
        )


def run(out_dir: Path, quick: bool = False) -> HumanGainsNumbers:
    """Write ``human_gains.md``, ``.csv`` and ``.png`` into ``out_dir`` (``quick``: 1.5 s of
    motion and 5 deg static steps instead of 6 s and 1 deg)."""
    out_dir = Path(out_dir)
    result = run_human_gains(duration_s=1.5 if quick else 6.0,
                             angle_step_deg=5.0 if quick else 1.0)
    table = markdown_table(result)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "human_gains.md").write_text(table)
    write_csv(result, out_dir / "human_gains.csv")
    plot(result, out_dir / "human_gains.png")
    static = result.worst("HUMAN", "static")
    return HumanGainsNumbers(static, result.worst("HUMAN", "motion"),
                             result.worst("CAT", "static") / static, table)
