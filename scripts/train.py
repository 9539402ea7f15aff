"""Train a PPO controller that feels the elbow only through its spindles; compare it with a
zero and a random policy on held-out targets.

    python scripts/train.py --timesteps 250000 --max-minutes 80 --out out/train_full \
        --curve docs/img/train_curve.png          # the documented full run (docs/envs.md)
    python scripts/train.py --timesteps 256 --smoke --out /tmp/smoke   # seconds

Prints progress lines (steps, steps/s, ETA, training |error|) and at the end one line per
policy ``<policy> mean_abs_err_deg=<float>``; writes ``eval.json``, ``curve.csv`` and the
policy (``policy.zip``) into ``--out`` and the learning curve PNG to ``--curve``. Needs the
``train`` extra. The protocol (held-out target bands, scoring) is
:mod:`proprio_env.experiments.training`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from proprio_env.experiments.training import POLICY_NAMES, TrainConfig, run


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
    config = TrainConfig(args.env, args.backend, args.afferent_source, args.timesteps,
                         args.max_minutes, args.seed, args.eval_episodes, args.curve_episodes,
                         args.eval_every)
    results = run(args.out, quick=args.smoke, config=config, curve=args.curve)
    steps, train_s = results["train"]["timesteps"], results["train"]["wall_s"]
    print(f"trained {steps} steps in {train_s / 60:.1f} min ({steps / train_s:.0f} steps/s)")
    for name in POLICY_NAMES:
        r = results[name]
        print(f"{name} mean_abs_err_deg={r['mean_abs_err_deg']:.2f} "
              f"(std {r['std_deg']:.2f}, {r['episodes']} held-out episodes)")
    return results


if __name__ == "__main__":
    main()
