"""The Golgi tendon organ (Ib): what the Lin & Crago (2002) model does, how exactly our step
follows it, and where the two published implementations part from it.

Figures (into ``out_dir``):

- ``gto_ramp_hold.png``: the cat preset's Ib on a force ramp-and-hold (0 -> 10 N in 0.5 s,
  held), the model's characteristic response (dynamic overshoot on the ramp, adaptation to
  the static log G1 ln(F/G2 + 1) over seconds), against the independent reference; and the
  human preset on brachialis forces (0 -> 400 N).
- ``gto_static.png``: static rate and sensitivity (pps/N) against force for CAT and the human
  BRA and TRImed scales.
- ``gto_accuracy.png``: RMS error of the step against the reference (scipy solve_ivp of the
  transfer function) for step sizes 1-20 ms on force steps, ramps and sinusoids.
- ``gto_implementations.png``: the same ramp-and-hold through our step, the OpenSim plugin's
  filter (40 x H(s): the numerator 68, 103.2, 16) and myogen's (the bilinear transform of
  H(s) at 1 ms, no low-pass, G1 = 40 pps).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spindle import tendon_organ as gto
from spindle.tendon_organ_params import (
    ARM26_MAX_ISOMETRIC_FORCE_N,
    CAT,
    HUMAN,
    TendonOrganParams,
    force_scales_N,
    static_rate_pps,
    static_sensitivity_pps_per_N,
)
from spindle.tendon_organ_reference import reference_rates

STEPS_S = (1e-3, 2e-3, 5e-3, 1e-2, 2e-2)


def rise(t0: float, rise_s: float, f0: float, f1: float):
    """Force (N) stepping from f0 to f1 along a line of ``rise_s`` from ``t0``."""
    return lambda t: f0 + (f1 - f0) * min(max((t - t0) / rise_s, 0.0), 1.0)


CASES = {
    "step up 0-10 N (20 ms rise)": rise(0.5, 0.02, 0.0, 10.0),
    "step down 10-1 N (20 ms rise)": rise(0.5, 0.02, 10.0, 1.0),
    "ramp 0-10 N over 1 s": rise(0.3, 1.0, 0.0, 10.0),
    "sinusoid 5 +- 4 N, 2 Hz": lambda t: 5.0 + 4.0 * np.sin(2 * np.pi * 2.0 * t),
}


def sampled(force, t: np.ndarray) -> np.ndarray:
    return np.array([force(x) for x in t])


def accuracy_table(duration_s: float) -> dict[str, list[float]]:
    """RMS |step - reference| (pps) per case and step size of :data:`STEPS_S` (CAT)."""
    t_ref = np.arange(round(duration_s / 1e-3) + 1) * 1e-3
    out = {}
    for name, force in CASES.items():
        ref = reference_rates(force, t_ref, CAT.force_scale_N, CAT)
        row = []
        for h in STEPS_S:
            stride = round(h / 1e-3)
            t = t_ref[::stride]
            ib = gto.simulate(sampled(force, t), h, CAT.force_scale_N, CAT)
            row.append(float(np.sqrt(np.mean((ib - ref[::stride]) ** 2))))
        out[name] = row
    return out


def opensim_variant(params: TendonOrganParams) -> TendonOrganParams:
    """The OpenSim plugin's filter: 40 x the numerator (its DC gain 40)."""
    return params.replace(num=tuple(40.0 * b for b in params.num), name="OpenSim plugin")


def myogen_rates(force_N: np.ndarray, dt_s: float, gain_pps: float = 40.0,
                 scale_N: float = 4.0) -> np.ndarray:
    """myogen's GTO (``_gto.pyx``): the log stage, then the bilinear transform of H(s) at
    ``dt_s``, started from zero (as myogen's is), clipped at 0."""
    T = dt_s
    den = 0.4 * T**2 + 4.4 * T + 4
    b = ((0.4 * T**2 + 5.16 * T + 6.8) / den, (0.8 * T**2 - 13.6) / den,
         (0.4 * T**2 - 5.16 * T + 6.8) / den)
    a = ((0.8 * T**2 - 8) / den, (0.4 * T**2 - 4.4 * T + 4) / den)
    r = gain_pps * np.log1p(np.maximum(force_N, 0.0) / scale_N)
    y = np.zeros_like(r)
    for k in range(len(r)):
        y[k] = (b[0] * r[k] + (b[1] * r[k - 1] if k >= 1 else 0.0)
                + (b[2] * r[k - 2] if k >= 2 else 0.0)
                - (a[0] * y[k - 1] if k >= 1 else 0.0) - (a[1] * y[k - 2] if k >= 2 else 0.0))
    return np.maximum(y, 0.0)


@dataclass(frozen=True)
class GtoNumbers:
    """What the experiment reports."""

    accuracy_pps: dict[str, list[float]]
    overshoot_ratio: float
    static_10N_pps: float
    sensitivity_pps_per_N: dict[str, float]
    force_scale_N: dict[str, float]
    opensim_over_ours: float

    def summary_md(self) -> str:
        head = "| case | " + " | ".join(f"{h * 1e3:g} ms" for h in STEPS_S) + " |"
        rows = [head, "|---" * (len(STEPS_S) + 1) + "|"]
        rows += [f"| {name} | " + " | ".join(f"{v:.4f}" for v in vals) + " |"
                 for name, vals in self.accuracy_pps.items()]
        sens = ", ".join(f"{k} {v:.3g} pps/N (G2 = {self.force_scale_N[k]:.1f} N)"
                         for k, v in self.sensitivity_pps_per_N.items())
        return (
            "RMS error of the step against the continuous system (pps, CAT, 2 s):\n\n"
            + "\n".join(rows)
            + f"\n\n- ramp-and-hold 0-10 N: peak / static = {self.overshoot_ratio:.3f}, "
            f"static rate at 10 N = {self.static_10N_pps:.2f} pps\n"
            f"- static sensitivity at 0 N: {sens}\n"
            f"- OpenSim plugin's hold rate / ours: {self.opensim_over_ours:.1f}\n"
        )


def _ramp_hold(params: TendonOrganParams, g2: float, f1: float, h: float, hold_s: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(0.0, 1.5 + hold_s + h / 2, h)
    force = rise(1.0, 0.5, 0.0, f1)
    ib = gto.simulate(sampled(force, t), h, g2, params)
    return t, ib, reference_rates(force, t[::10], g2, params)


def plot_ramp_hold(out: Path, hold_s: float) -> tuple[float, float]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g2_bra = float(force_scales_N(HUMAN, ARM26_MAX_ISOMETRIC_FORCE_N["BRA"]))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    ratio = static10 = 0.0
    for ax, (params, g2, f1, label) in zip(axes, (
            (CAT, CAT.force_scale_N, 10.0, "CAT, 0 -> 10 N"),
            (HUMAN, g2_bra, 400.0, f"HUMAN BRA (G2 = {g2_bra:.0f} N), 0 -> 400 N")),
            strict=True):
        t, ib, ref = _ramp_hold(params, g2, f1, 1e-3, hold_s)
        static = float(static_rate_pps(params, f1, g2))
        if params is CAT:
            ratio, static10 = float(ib.max() / static), static
        ax.plot(t, ib, lw=1.2, label="our step (1 ms)")
        ax.plot(t[::10], ref, "k:", lw=1.0, label="reference (solve_ivp)")
        ax.axhline(static, color="0.5", lw=0.8, ls="--", label="static G1 ln(F/G2+1)")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("Ib (pps)")
        ax.set_title(label, fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return ratio, static10


def plot_static(out: Path) -> tuple[dict[str, float], dict[str, float]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scales = {"CAT (soleus)": (CAT, CAT.force_scale_N)}
    for m, f in ARM26_MAX_ISOMETRIC_FORCE_N.items():
        scales[f"HUMAN {m}"] = (HUMAN, float(force_scales_N(HUMAN, f)))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    sens, g2s = {}, {}
    for name, (params, g2) in scales.items():
        fmax = params.reference_max_force_N * g2 / params.force_scale_N
        f = np.linspace(0, fmax, 400)
        axes[0].plot(f / fmax * 100, static_rate_pps(params, f, g2), label=name)
        axes[1].semilogy(f / fmax * 100, static_sensitivity_pps_per_N(params, f, g2),
                         label=name)
        sens[name] = float(static_sensitivity_pps_per_N(params, 0.0, g2))
        g2s[name] = g2
    axes[0].set_ylabel("static Ib (pps)")
    axes[1].set_ylabel("static sensitivity (pps/N)")
    for ax in axes:
        ax.set_xlabel("tendon force (% of maximum isometric force)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return sens, g2s


def plot_accuracy(out: Path, table: dict[str, list[float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for name, vals in table.items():
        ax.loglog(np.array(STEPS_S) * 1e3, np.maximum(vals, 1e-7), "o-", label=name)
    ax.axhline(0.1, color="k", lw=0.8, ls="--", label="0.1 pps")
    ax.set_xlabel("step (ms)")
    ax.set_ylabel("RMS error vs reference (pps)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)


def plot_implementations(out: Path, hold_s: float) -> float:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h = 1e-3
    t = np.arange(0.0, 1.5 + hold_s + h / 2, h)
    f = sampled(rise(1.0, 0.5, 0.0, 10.0), t)
    ours = gto.simulate(f, h, 4.0, CAT)
    opensim = gto.simulate(f, h, 4.0, opensim_variant(CAT))
    myogen = myogen_rates(f, h)
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    ax.semilogy(t, np.maximum(ours, 1e-2), label="Lin & Crago as here (CAT: G1 60, H(0) 1)")
    ax.semilogy(t, np.maximum(opensim, 1e-2), label="OpenSim plugin's filter (40 H(s))")
    ax.semilogy(t, np.maximum(myogen, 1e-2), label="myogen (G1 40, bilinear, no low-pass)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("Ib (pps)")
    ax.set_ylim(0.5, 1e4)
    ax.set_title("0 -> 10 N ramp-and-hold, G2 = 4 N", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return float(opensim[-1] / ours[-1])


def run(out_dir: Path, quick: bool = False) -> GtoNumbers:
    """Write the four figures into ``out_dir``; ``quick``: 3 s holds and 1 s accuracy runs
    instead of 12 s and 2 s."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    hold_s = 3.0 if quick else 12.0
    ratio, static10 = plot_ramp_hold(out_dir / "gto_ramp_hold.png", hold_s)
    sens, g2s = plot_static(out_dir / "gto_static.png")
    table = accuracy_table(1.0 if quick else 2.0)
    plot_accuracy(out_dir / "gto_accuracy.png", table)
    ratio_opensim = plot_implementations(out_dir / "gto_implementations.png", hold_s)
    return GtoNumbers(table, ratio, static10, sens, g2s, ratio_opensim)
