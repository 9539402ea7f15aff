"""Train a PPO controller that feels the elbow only through its spindles; compare it with a
zero and a random policy on held-out targets.

Training targets are drawn from 15-115 deg *minus* the held-out bands (:data:`HELD_OUT_BANDS`);
evaluation episodes use targets spread evenly over those bands only, from seeded initial
angles. The score of an episode is its mean |elbow angle - target| over the last second
(hold phase, 50 steps at 50 Hz); the reported figure is the mean over episodes.

Two engines train on the same protocol and write the same files (``eval.json``,
``curve.csv``, the curve PNG, the policy): stable-baselines3 here (:func:`run`; the ``train``
extra: stable-baselines3, a CPU torch, matplotlib, tqdm), one process, torch on one thread,
stepping the native vector env (``gym.make_vec``) through
:class:`proprio_env.training.sb3_vec.SB3VectorEnv`;
and Ray RLlib (:mod:`proprio_env.training.rllib`, the ``distributed`` extra).
Both collect :data:`ROLLOUT_STEPS` env steps per PPO update whatever the number of envs.
Progress lines (steps, steps/s, ETA, training |error|) are printed; the command line is
``python scripts/train.py``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND
from spindle.number_rule import positive_int, real_scalar

HELD_OUT_BANDS = ((35.0, 40.0), (60.0, 65.0), (85.0, 90.0))
"""Target bands (deg) never drawn during training; evaluation targets come only from them."""
TARGET_SPAN_DEG = (15.0, 115.0)
HOLD_STEPS = 50
"""The last 50 steps (1 s at 50 Hz) of an episode score it."""
ROLLOUT_STEPS = 2048
"""Env steps per PPO update (over all envs: SB3's ``n_steps * num_envs``, RLlib's train batch)."""
SMOKE_ROLLOUT_STEPS = 128
"""The same for ``quick`` (smoke) runs."""
CURVE_COLUMNS = ("timesteps", "elapsed_s", "train_abs_err_deg", "held_out_abs_err_deg")
MAX_SEED = 2**31 - 1
"""Largest ``seed``: the runs add sub-env and runner offsets to it, and numpy's legacy seeding
(stable-baselines3's ``set_random_seed``) takes at most 2^32 - 1."""


def check_env_id(env_id: str) -> str:
    """``env_id`` if Gymnasium knows it (``module:id`` imports ``module`` first, as
    ``gymnasium.make`` does), else ValueError naming the registered project ids."""
    import importlib

    import gymnasium as gym

    import proprio_env  # registers the project's ids (light: no MuJoCo)

    module, _, name = env_id.rpartition(":")
    try:
        if module:
            importlib.import_module(module)
    except ImportError as exc:
        raise ValueError(f"env_id={env_id!r}: its module {module!r} does not import "
                         f"({exc})") from None
    if name not in gym.registry:
        raise ValueError(f"env_id={env_id!r} is not a registered Gymnasium env (the project's: "
                         f"{', '.join(proprio_env.ENV_IDS)})")
    return env_id


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


def make_vector_env(env_id: str, env_kwargs: dict[str, Any], num_envs: int, ranges=None,
                    vectorization_mode: str | None = None):
    """``gym.make_vec(env_id, num_envs)``: the env's own vector env when it declares one
    (``vector_entry_point``), else Gymnasium's ``SyncVectorEnv``; or ``vectorization_mode``."""
    import gymnasium as gym

    import proprio_env  # noqa: F401  (registers the envs)

    kwargs = dict(env_kwargs)
    if ranges is not None:
        kwargs["target_ranges_deg"] = ranges
    return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode=vectorization_mode,
                        **kwargs)


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


CURVE_SEED = 10_000
"""Seed of the learning curve's held-out episodes."""
EVAL_SEED = 20_000
"""Seed of the final held-out evaluation."""


def zero_policy(obs, env):
    low, high = env.action_space.low, env.action_space.high
    return np.clip(np.zeros(env.action_space.shape, dtype=np.float32), low, high)


def random_policy(obs, env):
    return env.action_space.sample()


def whole_rollouts(timesteps: int, rollout_steps: int) -> int:
    """The env steps a run of ``timesteps`` really takes: both engines only stop after a
    whole rollout (train batch), so ``timesteps`` rounded up to a multiple of
    ``rollout_steps`` (250,000 at 2048 per rollout: 123 rollouts, 251,904 steps)."""
    return -(-int(timesteps) // int(rollout_steps)) * int(rollout_steps)


def progress_line(steps: int, total: int, elapsed_s: float, train_err: float,
                  held: float) -> str:
    """One progress line (both engines print the same)."""
    rate = steps / max(elapsed_s, 1e-9)
    eta = max(total - steps, 0) / max(rate, 1e-9)
    return (f"steps {steps:7d}/{total} | {rate:6.1f} steps/s | elapsed {elapsed_s / 60:5.1f} min"
            f" | ETA {eta / 60:5.1f} min | train |err| {train_err:6.2f} deg"
            + (f" | held-out |err| {held:6.2f} deg" if not math.isnan(held) else ""))


def build_callback(config: TrainConfig, env_kwargs: dict[str, Any], curve_rows: list,
                   start: float, rollout_steps: int):
    from stable_baselines3.common.callbacks import BaseCallback

    total = whole_rollouts(config.timesteps, rollout_steps)

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
            return elapsed < config.max_minutes * 60

        def _on_rollout_end(self) -> None:
            steps = self.num_timesteps
            elapsed = time.perf_counter() - start
            train_err = float(np.mean(self._errors)) if self._errors else math.nan
            self._errors = []
            held = math.nan
            if steps >= self._next_eval:
                held = evaluate(lambda o, e: self.model.predict(o, deterministic=True)[0],
                                config.env_id, env_kwargs, config.curve_episodes,
                                seed=CURVE_SEED)["mean_abs_err_deg"]
                self._next_eval = steps + config.eval_every
            curve_rows.append((steps, elapsed, train_err, held))
            print(progress_line(steps, total, elapsed, train_err, held), flush=True)

    return Progress()


def plot_curve(rows, results, path: Path, engine: str = "sb3") -> None:
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
    env_name = results["train"]["env"].split("/")[-1]
    ax.set_title(f"PPO ({engine}) on {env_name}: proprioception only (Ia, II + target)",
                 fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


@dataclass(frozen=True)
class TrainConfig:
    """One training run: the env, its afferent path, the budget and the evaluation."""

    env_id: str = "proprio_env/ElbowReach-v0"
    backend: str = DEFAULT_BACKEND
    afferent_source: str | None = None
    """exact | reduced | encoder (None: the env's default)"""
    timesteps: int = 250_000
    max_minutes: float = 80.0
    """Training stops after this wall time."""
    seed: int = 0
    eval_episodes: int = 30
    curve_episodes: int = 6
    eval_every: int = 20_000
    num_envs: int = 8
    """Envs stepped together in one process (SB3: the vector env; RLlib: per env runner)."""

    def __post_init__(self) -> None:
        # everything a run needs is checked here, before an env, a model or Ray exists
        if not (isinstance(self.env_id, str) and self.env_id):
            raise ValueError(f"env_id={self.env_id!r} must be a Gymnasium env id")
        check_env_id(self.env_id)
        if not (isinstance(self.backend, str) and self.backend in BACKEND_CHOICES):
            raise ValueError(f"backend={self.backend!r} is not one of {BACKEND_CHOICES}")
        from proprio_env.envs.afferents import SOURCES  # imports MuJoCo: only when checked

        if self.afferent_source is not None and self.afferent_source not in SOURCES:
            raise ValueError(f"afferent_source={self.afferent_source!r} is not one of "
                             f"{SOURCES}")
        for name in ("timesteps", "eval_episodes", "curve_episodes", "eval_every"):
            object.__setattr__(self, name, positive_int(name, getattr(self, name)))
        object.__setattr__(self, "num_envs", positive_int("num_envs", self.num_envs,
                                                          high=SMOKE_ROLLOUT_STEPS))
        if (isinstance(self.seed, bool) or not isinstance(self.seed, int)
                or not 0 <= self.seed <= MAX_SEED):
            raise ValueError(f"seed={self.seed!r} must be an integer in 0..{MAX_SEED}")
        object.__setattr__(self, "max_minutes", real_scalar("max_minutes", self.max_minutes,
                                                            low=0.0, low_open=True))

    def env_kwargs(self) -> dict[str, Any]:
        kwargs: dict[str, Any] = {"backend": self.backend}
        if self.afferent_source is not None:
            kwargs["afferent_source"] = self.afferent_source
        return kwargs


POLICY_NAMES = ("ppo", "zero", "random")


def sb3_ppo_kwargs(num_envs: int, quick: bool = False) -> dict[str, Any]:
    """SB3 PPO's settings: ``n_steps`` per env so that a rollout holds :data:`ROLLOUT_STEPS`
    (``quick``: :data:`SMOKE_ROLLOUT_STEPS`) env steps whatever ``num_envs`` is."""
    rollout = SMOKE_ROLLOUT_STEPS if quick else ROLLOUT_STEPS
    if rollout % num_envs:
        raise ValueError(f"num_envs={num_envs} must divide the rollout of {rollout} env steps "
                         "(a power of two up to 128 does)")
    kwargs: dict[str, Any] = dict(n_steps=rollout // num_envs, batch_size=64, gamma=0.98,
                                  policy_kwargs=dict(log_std_init=-0.5))
    if quick:
        kwargs.update(batch_size=32, n_epochs=2)
    return kwargs


def quick_config(config: TrainConfig) -> TrainConfig:
    """The smoke run's evaluation sizes."""
    return dataclasses.replace(config, eval_episodes=3, curve_episodes=3)


def evaluate_policies(ppo_policy, config: TrainConfig) -> dict[str, Any]:
    """The trained ``ppo_policy(obs, env) -> action`` and the zero and random policies on the
    held-out targets (:func:`evaluate`, seed :data:`EVAL_SEED`)."""
    policies = {"ppo": ppo_policy, "zero": zero_policy, "random": random_policy}
    return {name: evaluate(policy, config.env_id, config.env_kwargs(), config.eval_episodes,
                           seed=EVAL_SEED)
            for name, policy in policies.items()}


def train_record(config: TrainConfig, engine: str, timesteps: int, wall_s: float,
                 **extra: Any) -> dict[str, Any]:
    """``eval.json``'s ``"train"`` entry."""
    return {"engine": engine, "timesteps": int(timesteps), "wall_s": wall_s,
            "held_out_bands_deg": HELD_OUT_BANDS, "env": config.env_id,
            "afferent_source": config.afferent_source, "backend": config.backend,
            "seed": config.seed, "num_envs": config.num_envs, **extra}


def write_results(out_dir: Path, results: dict[str, Any], rows: list, curve_path: Path,
                  engine: str) -> None:
    """``eval.json``, ``curve.csv`` into ``out_dir`` and the learning curve to ``curve_path``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "eval.json").write_text(json.dumps(results, indent=2))
    with (out_dir / "curve.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CURVE_COLUMNS)
        writer.writerows(rows)
    if rows:
        plot_curve(rows, results, curve_path, engine)


def run(out_dir: Path, quick: bool = False, config: TrainConfig | None = None,
        curve: Path | None = None) -> dict[str, Any]:
    """Train PPO with stable-baselines3 on ``config.num_envs`` envs of the vector env,
    evaluate it and the zero and random policies on the held-out targets; write
    ``policy.zip``, ``eval.json``, ``curve.csv`` into ``out_dir`` and the learning curve to
    ``curve`` (default ``out_dir/curve.png``). ``quick``: tiny rollouts and evaluations (the
    test suite's smoke run). Returns what ``eval.json`` holds."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    from proprio_env.training.sb3_vec import SB3VectorEnv

    config = TrainConfig() if config is None else config
    if quick:
        config = quick_config(config)
    ppo_kwargs = sb3_ppo_kwargs(config.num_envs, quick)
    out_dir = Path(out_dir)
    torch.set_num_threads(1)
    env_kwargs = config.env_kwargs()
    out_dir.mkdir(parents=True, exist_ok=True)
    curve_path = curve if curve is not None else out_dir / "curve.png"
    venv = make_vector_env(config.env_id, env_kwargs, config.num_envs, training_ranges())
    env = VecMonitor(SB3VectorEnv(venv))
    model = PPO("MlpPolicy", env, seed=config.seed, verbose=0, device="cpu", **ppo_kwargs)
    rows: list[tuple[int, float, float, float]] = []
    start = time.perf_counter()
    rollout_steps = ppo_kwargs["n_steps"] * config.num_envs
    print(f"training PPO (stable-baselines3, {config.num_envs} envs x {ppo_kwargs['n_steps']} "
          f"steps per rollout) on {config.env_id} for up to {config.timesteps} steps "
          f"({whole_rollouts(config.timesteps, rollout_steps)}: whole rollouts) or "
          f"{config.max_minutes:g} min (held-out bands {HELD_OUT_BANDS} deg)", flush=True)
    model.learn(config.timesteps,
                callback=build_callback(config, env_kwargs, rows, start, rollout_steps))
    train_s = time.perf_counter() - start
    model.save(out_dir / "policy.zip")
    env.close()

    results: dict[str, Any] = evaluate_policies(
        lambda o, e: model.predict(o, deterministic=True)[0], config)
    results["train"] = train_record(config, "sb3", model.num_timesteps, train_s,
                                    n_steps=ppo_kwargs["n_steps"],
                                    vector_env=type(venv.unwrapped).__name__)
    write_results(out_dir, results, rows, curve_path, "sb3")
    return results
