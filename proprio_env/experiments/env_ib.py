"""The v1 envs' force sense over an episode: tendon forces and Ib beside Ia (``docs/envs.md``).

ElbowReach-v1 under alternating BRA / TRImed excitation (0.5 s each), ProsthesisElbow-v1
under servo commands stepping between 30 and 100 deg every 0.5 s; both from rest at 60 deg,
seed 0. Command line: ``PYTHONPATH=. python scripts/env_ib_figure.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

STEPS = 100
"""Env steps per trace (2 s at 50 Hz)."""


@dataclass
class Trace:
    """One env's episode: time (s), angle (deg), forces (N), Ib and Ia (pps), (T,) / (T, 2)."""

    env_id: str
    t_s: np.ndarray
    angle_deg: np.ndarray
    force_N: np.ndarray
    ib_pps: np.ndarray
    ia_pps: np.ndarray


def actions(env_id: str, steps: int = STEPS) -> np.ndarray:
    half = (np.arange(steps) // 25) % 2 == 0
    if "Prosthesis" in env_id:  # commands 30 / 100 deg: a = (cmd - 65) / 65
        return np.where(half, (30 - 65) / 65, (100 - 65) / 65)[:, None].astype(np.float32)
    return np.stack([np.where(half, 0.8, 0.0), np.where(half, 0.0, 0.8)], 1).astype(
        np.float32)


def run_trace(env_id: str, backend: str = "auto", steps: int = STEPS) -> Trace:
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    env = gym.make(env_id, backend=backend)
    _, info = env.reset(seed=0, options={"angle_deg": 60.0, "target_deg": 60.0})
    infos = [info]
    for a in actions(env_id, steps):
        infos.append(env.step(a)[4])
    env.close()

    def col(key: str) -> np.ndarray:
        return np.array([i[key] for i in infos])

    return Trace(env_id, col("time_s"), col("angle_deg"), col("force_N"), col("ib_pps"),
                 col("ia_pps"))


def figure(traces: list[Trace], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(traces), figsize=(5.5 * len(traces), 7.5), sharex=True)
    for j, tr in enumerate(traces):
        ax = axes[:, j]
        ax[0].plot(tr.t_s, tr.angle_deg, "k")
        ax[0].set_ylabel("elbow flexion (deg)")
        ax[0].set_title(tr.env_id.split("/")[1])
        for m, (name, colour) in enumerate((("BRA", "C0"), ("TRImed", "C3"))):
            ax[1].plot(tr.t_s, tr.force_N[:, m], colour, label=name)
            ax[2].plot(tr.t_s, tr.ib_pps[:, m], colour, label=f"Ib {name}")
            ax[2].plot(tr.t_s, tr.ia_pps[:, m], colour, ls=":", label=f"Ia {name}")
        ax[1].set_ylabel("tendon force (N)")
        ax[2].set_ylabel("rate (pps)")
        ax[2].set_xlabel("time (s)")
        ax[1].legend(fontsize=8)
        ax[2].legend(fontsize=8, ncol=2)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def summary(traces: list[Trace]) -> str:
    lines = ["| env | max force BRA / TRImed (N) | max Ib BRA / TRImed (pps) "
             "| Ib at the end (pps) |", "|---|---|---|---|"]
    for tr in traces:
        f, ib = tr.force_N.max(0), tr.ib_pps.max(0)
        lines.append(f"| {tr.env_id} | {f[0]:.0f} / {f[1]:.0f} | {ib[0]:.1f} / {ib[1]:.1f} | "
                     f"{tr.ib_pps[-1, 0]:.1f} / {tr.ib_pps[-1, 1]:.1f} |")
    return "\n".join(lines)
