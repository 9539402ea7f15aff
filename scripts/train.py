"""Train a PPO controller that feels the elbow only through its spindles; compare it with a
zero and a random policy on held-out targets.

    python scripts/train.py --timesteps 250000 --out out/train \
        --curve docs/img/train_curve.png          # the documented full run (docs/envs.md)
    python scripts/train.py --smoke --out /tmp/smoke   # seconds (256 env steps)
    python scripts/train.py --engine rllib --smoke --out /tmp/smoke_rllib   # about a minute
    python scripts/train.py --engine rllib --num-env-runners 2 --checkpoint-dir ckpt \
        --out out/train_rllib                     # docs/training.md

Engines: ``sb3`` (stable-baselines3 in one process on the vector env; extra ``train``) and
``rllib`` (Ray RLlib, env runners each stepping a vector env, local Ray or ``--address``;
extra ``distributed``). Prints progress lines (steps, steps/s, ETA, training |error|) and at
the end one line per policy ``<policy> mean_abs_err_deg=<float>``; writes ``eval.json``,
``curve.csv`` and the policy (``policy.zip`` for sb3, the RLModule directory ``policy/`` for
rllib) into ``--out`` and the learning curve PNG to ``--curve``. The protocol (held-out
target bands, scoring) is :mod:`proprio_env.training.sb3`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from proprio_env.training.rllib import RLlibOptions, check_resume
from proprio_env.training.rllib import run as run_rllib
from proprio_env.training.sb3 import POLICY_NAMES, TrainConfig, sb3_ppo_kwargs
from proprio_env.training.sb3 import run as run_sb3
from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND

FULL_TIMESTEPS = 250_000
"""Env steps of the documented full run."""
SMOKE_TIMESTEPS = 256
"""Env steps of ``--smoke`` without ``--timesteps``: two smoke rollouts, seconds to a minute."""

def checked_run(args: argparse.Namespace) -> tuple[TrainConfig, RLlibOptions | None]:
    """The run's settings from the parsed command line, every one checked (ValueError
    naming the option otherwise); nothing is built."""
    if args.timesteps is None:
        args.timesteps = SMOKE_TIMESTEPS if args.smoke else FULL_TIMESTEPS
    if args.engine == "sb3":
        given = [name for name, value in (("--address", args.address),
                                          ("--num-envs-per-runner", args.num_envs_per_runner),
                                          ("--checkpoint-dir", args.checkpoint_dir))
                 if value is not None] + (["--resume"] if args.resume else [])
        if given:
            raise ValueError(f"{', '.join(given)} belong to --engine rllib")
        num_envs = 8 if args.num_envs is None else args.num_envs
    else:
        if args.num_envs is not None:
            raise ValueError("--num-envs belongs to --engine sb3 (rllib: --num-envs-per-runner)")
        num_envs = 8 if args.num_envs_per_runner is None else args.num_envs_per_runner
    if args.out.is_file():
        raise ValueError(f"--out {str(args.out)!r} is a file; it must be a folder")
    if args.curve is not None and args.curve.is_dir():
        raise ValueError(f"--curve {str(args.curve)!r} is a folder; it must be a PNG's path")
    config = TrainConfig(args.env, args.backend, args.afferent_source, args.timesteps,
                         args.max_minutes, args.seed, args.eval_episodes, args.curve_episodes,
                         args.eval_every, num_envs)
    if args.engine == "sb3":
        sb3_ppo_kwargs(num_envs, args.smoke)
        return config, None
    options = RLlibOptions(args.address, args.num_cpus, args.num_env_runners,
                           args.checkpoint_dir, args.checkpoint_every, args.resume)
    check_resume(config, options)
    return config, options


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--engine", choices=("sb3", "rllib"), default="sb3")
    parser.add_argument("--env", default="proprio_env/ElbowReach-v0")
    parser.add_argument("--backend", choices=BACKEND_CHOICES, default=DEFAULT_BACKEND,
                        help="spindle chain backend (c: compiled on first use; needs a C "
                             "compiler)")
    parser.add_argument("--afferent-source", default=None,
                        help="exact | reduced | encoder (default: the env's)")
    parser.add_argument("--timesteps", type=int, default=None,
                        help=f"env steps to train (default {FULL_TIMESTEPS}; with --smoke "
                             f"{SMOKE_TIMESTEPS})")
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
    sb3 = parser.add_argument_group("sb3 engine")
    sb3.add_argument("--num-envs", type=int, default=None,
                     help="envs in the vector env (default 8; divides the 2048-step rollout)")
    rllib = parser.add_argument_group("rllib engine")
    rllib.add_argument("--address", default=None,
                       help="a running Ray cluster (e.g. auto, host:6379); default: start a "
                            "local Ray instance with --num-cpus CPUs")
    rllib.add_argument("--num-cpus", type=int, default=2, help="CPUs of the local Ray instance")
    rllib.add_argument("--num-env-runners", type=int, default=1)
    rllib.add_argument("--num-envs-per-runner", type=int, default=None,
                       help="envs in each runner's vector env (default 8)")
    rllib.add_argument("--checkpoint-dir", type=Path, default=None)
    rllib.add_argument("--checkpoint-every", type=int, default=10,
                       help="iterations (2048 env steps each) between checkpoints")
    rllib.add_argument("--resume", action="store_true",
                       help="restore --checkpoint-dir and train on to --timesteps")
    args = parser.parse_args(argv)
    try:  # every argument checked before an env, a model or Ray exists (exit 2, as argparse)
        config, options = checked_run(args)
    except ValueError as exc:
        parser.error(str(exc))
    if args.engine == "sb3":
        results = run_sb3(args.out, quick=args.smoke, config=config, curve=args.curve)
    else:
        results = run_rllib(args.out, quick=args.smoke, config=config, options=options,
                            curve=args.curve)
    steps, train_s = results["train"]["timesteps"], results["train"]["wall_s"]
    print(f"trained {steps} steps in {train_s / 60:.1f} min ({steps / train_s:.0f} steps/s)")
    for name in POLICY_NAMES:
        r = results[name]
        print(f"{name} mean_abs_err_deg={r['mean_abs_err_deg']:.2f} "
              f"(std {r['std_deg']:.2f}, {r['episodes']} held-out episodes)")
    return results


if __name__ == "__main__":
    main()
