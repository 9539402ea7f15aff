"""Train a PPO controller that feels the elbow only through its spindles; compare it with a
zero and a random policy on held-out targets.

Training targets are drawn from 15-115 deg *minus* the held-out bands (:data:`HELD_OUT_BANDS`);
evaluation episodes use targets spread evenly over those bands only, from seeded initial
angles. The score of an episode is its mean |elbow angle - target| over the last second
(hold phase, 50 steps at 50 Hz); the reported figure is the mean over episodes.

Needs the ``train`` extra (stable-baselines3, a CPU torch, matplotlib, tqdm). Runs on one
core (torch threads = 1, one env in-process).

    python scripts/train.py --timesteps 250000 --max-minutes 80 --out out/train_full \
        --curve docs/img/train_curve.png          # the documented full run (docs/envs.md)
    python scripts/train.py --timesteps 256 --smoke --out /tmp/smoke   # seconds

Prints progress lines (steps, steps/s, ETA, training |error|) and at the end one line per
policy ``<policy> mean_abs_err_deg=<float>``; writes ``eval.json``, ``curve.csv`` and the
policy (``policy.zip``) into ``--out`` and the learning curve PNG to ``--curve``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

HELD_OUT_BANDS = ((35.0, 40.0), (60.0, 65.0), (85.0, 90.0))
"""Target bands (deg) never drawn during training; evaluation targets come only from them."""
TARGET_SPAN_DEG = (15.0, 115.0)
HOLD_STEPS = 50
"""The last 50 steps (1 s at 50 Hz) of an episode score it."""


def training_ranges(span: tuple[float, float] = TARGET_SPAN_DEG,
                    held_out: tuple[tuple[float, float], ...] = HELD_OUT_BANDS
                    ) -> tuple[tuple[float, float], ...]:
    """``span`` minus the ``held_out`` bands, as (low, high) intervals (deg)."""
    out, lo = [], span[0]
    for a, b in sorted(held_out):
        if a > lo:
            out.append((lo, a))
        lo = max(lo, b)
    if lo < span[1]:
        out.append((lo, span[1]))
    return tuple(out)


def held_out_targets(n: int) -> np.ndarray:
    """``n`` targets (deg) spread evenly over the held-out bands (band by band)."""
    per_band = np.array_split(np.arange(n), len(HELD_OUT_BANDS))
    targets = []
    for (a, b), idx in zip(HELD_OUT_BANDS, per_band, strict=True):
        k = len(idx)
        targets += list(a + (b - a) * (np.arange(k) + 0.5) / max(k, 1))
    return np.array(targets)


def make_env(env_id: str, env_kwargs: dict[str, Any], ranges=None, seed: int | None = None):
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    kwargs = dict(env_kwargs)
    if ranges is not None:
        kwargs["target_ranges_deg"] = ranges
    env = gym.make(env_id, **kwargs)
    if seed is not None:
        env.action_space.seed(seed)
    return env


def evaluate(policy, env_id: str, env_kwargs: dict[str, Any], n_episodes: int, seed: int
             ) -> dict[str, float]:
    """Mean (and spread) over held-out episodes of the hold-phase mean |error| (deg).

    ``policy(obs, env) -> action``; episode i has target ``held_out_targets(n)[i]`` and an
    initial angle drawn by ``reset(seed=seed + i)``.
    """
    env = make_env(env_id, env_kwargs, seed=seed)
    scores = []
    for i, target in enumerate(held_out_targets(n_episodes)):
        obs, _ = env.reset(seed=seed + i, options={"target_deg": float(target)})
        errors = []
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs, env))
            errors.append(abs(info["angle_error_deg"]))
            done = terminated or truncated
        scores.append(float(np.mean(errors[-HOLD_STEPS:])))
    env.close()
    return {"mean_abs_err_deg": float(np.mean(scores)), "std_deg": float(np.std(scores)),
            "episodes": n_episodes}


def zero_policy(obs, env):
    low, high = env.action_space.low, env.action_space.high
    return np.clip(np.zeros(env.action_space.shape, dtype=np.float32), low, high)


def random_policy(obs, env):
    return env.action_space.sample()


def build_callback(args, env_id, env_kwargs, curve_rows, start):
    from stable_baselines3.common.callbacks import BaseCallback

    class Progress(BaseCallback):
        """Progress lines, a wall-clock stop and the learning curve."""

        def __init__(self):
            super().__init__()
            self._errors: list[float] = []
            self._next_eval = 0

        def _on_step(self) -> bool:
            for info in self.locals["infos"]:
                self._errors.append(abs(info["angle_error_deg"]))
            elapsed = time.perf_counter() - start
            return elapsed < args.max_minutes * 60

        def _on_rollout_end(self) -> None:
            steps = self.num_timesteps
            elapsed = time.perf_counter() - start
            rate = steps / max(elapsed, 1e-9)
            train_err = float(np.mean(self._errors)) if self._errors else math.nan
            self._errors = []
            held = math.nan
            if steps >= self._next_eval:
                held = evaluate(lambda o, e: self.model.predict(o, deterministic=True)[0],
                                env_id, env_kwargs, args.curve_episodes, seed=10_000)[
                    "mean_abs_err_deg"]
                self._next_eval = steps + args.eval_every
            curve_rows.append((steps, elapsed, train_err, held))
            eta = (args.timesteps - steps) / max(rate, 1e-9)
            print(f"steps {steps:7d}/{args.timesteps} | {rate:6.1f} steps/s | "
                  f"elapsed {elapsed / 60:5.1f} min | ETA {eta / 60:5.1f} min | "
                  f"train |err| {train_err:6.2f} deg"
                  + (f" | held-out |err| {held:6.2f} deg" if not math.isnan(held) else ""),
                  flush=True)

    return Progress()


def plot_curve(rows, results, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([r[0] for r in rows], dtype=float)
    train = np.array([r[2] for r in rows])
    held = np.array([r[3] for r in rows])
    fig, ax = plt.subplots(figsize=(6, 3.6))
    ax.plot(steps, train, lw=1, label="training episodes, mean |error| (all steps)")
    ok = ~np.isnan(held)
    ax.plot(steps[ok], held[ok], "o-", ms=3, label="held-out targets, last 1 s")
    for name, ls in (("zero", "--"), ("random", ":")):
        ax.axhline(results[name]["mean_abs_err_deg"], color="0.4", ls=ls,
                   label=f"{name} policy, held-out ({results[name]['mean_abs_err_deg']:.1f}°)")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("|elbow angle - target| (deg)")
    ax.set_yscale("log")
    ax.set_title("PPO on ElbowReach-v0: proprioception only (Ia, II + target)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="proprio_env/ElbowReach-v0")
    parser.add_argument("--backend", choices=("c", "numpy"), default="c",
                        help="spindle chain backend (c: compiled on first use; needs a C "
                             "compiler)")
    parser.add_argument("--afferent-source", default=None,
                        help="exact | reduced | encoder (default: the env's)")
    parser.add_argument("--timesteps", type=int, default=250_000)
    parser.add_argument("--max-minutes", type=float, default=80.0,
                        help="stop training after this wall time (min)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=30)
    parser.add_argument("--curve-episodes", type=int, default=6)
    parser.add_argument("--eval-every", type=int, default=20_000)
    parser.add_argument("--out", type=Path, default=Path("out/train"))
    parser.add_argument("--curve", type=Path, default=None,
                        help="learning-curve PNG (default: <out>/curve.png)")
    parser.add_argument("--smoke", action="store_true",
                        help="tiny rollouts and evaluations (tests)")
    args = parser.parse_args(argv)
    if args.timesteps < 1 or args.max_minutes <= 0 or args.eval_episodes < 1:
        parser.error("--timesteps, --max-minutes and --eval-episodes must be positive")

    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.monitor import Monitor

    torch.set_num_threads(1)
    env_kwargs: dict[str, Any] = {"backend": args.backend}
    if args.afferent_source is not None:
        env_kwargs["afferent_source"] = args.afferent_source
    args.out.mkdir(parents=True, exist_ok=True)
    curve_path = args.curve if args.curve is not None else args.out / "curve.png"
    env = Monitor(make_env(args.env, env_kwargs, training_ranges(), seed=args.seed))
    ppo_kwargs: dict[str, Any] = dict(n_steps=2048, batch_size=64, gamma=0.98,
                                      policy_kwargs=dict(log_std_init=-0.5))
    if args.smoke:
        ppo_kwargs.update(n_steps=128, batch_size=32, n_epochs=2)
        args.eval_episodes, args.curve_episodes = 3, 3
    model = PPO("MlpPolicy", env, seed=args.seed, verbose=0, device="cpu", **ppo_kwargs)
    rows: list[tuple[int, float, float, float]] = []
    start = time.perf_counter()
    print(f"training PPO on {args.env} for up to {args.timesteps} steps or "
          f"{args.max_minutes:g} min (held-out bands {HELD_OUT_BANDS} deg)", flush=True)
    model.learn(args.timesteps,
                callback=build_callback(args, args.env, env_kwargs, rows, start))
    train_s = time.perf_counter() - start
    model.save(args.out / "policy.zip")
    env.close()

    results: dict[str, Any] = {}
    policies = {
        "ppo": lambda o, e: model.predict(o, deterministic=True)[0],
        "zero": zero_policy,
        "random": random_policy,
    }
    for name, policy in policies.items():
        results[name] = evaluate(policy, args.env, env_kwargs, args.eval_episodes,
                                 seed=20_000)
    results["train"] = {"timesteps": int(model.num_timesteps), "wall_s": train_s,
                        "held_out_bands_deg": HELD_OUT_BANDS, "env": args.env,
                        "afferent_source": args.afferent_source, "backend": args.backend,
                        "seed": args.seed}
    (args.out / "eval.json").write_text(json.dumps(results, indent=2))
    with (args.out / "curve.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["timesteps", "elapsed_s", "train_abs_err_deg", "held_out_abs_err_deg"])
        writer.writerows(rows)
    if rows:
        plot_curve(rows, results, curve_path)
    print(f"trained {model.num_timesteps} steps in {train_s / 60:.1f} min "
          f"({model.num_timesteps / train_s:.0f} steps/s)")
    for name in policies:
        r = results[name]
        print(f"{name} mean_abs_err_deg={r['mean_abs_err_deg']:.2f} "
              f"(std {r['std_deg']:.2f}, {r['episodes']} held-out episodes)")
    return results


if __name__ == "__main__":
    main()
