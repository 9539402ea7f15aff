"""Soak test of the envs: many random-action steps; no NaN/inf and the state stays bounded.

    python scripts/soak_env.py --steps 1000000 [--env proprio_env/ElbowReach-v0] [--seed 0]
        [--max-minutes M] [--num-envs N [--num-threads T]]

With ``--num-envs N`` the native vector env (``gymnasium.make_vec``) is soaked instead:
``--steps`` env steps, N per vector step, random and corner actions, autoresets; every
observation finite and inside the observation space.

Prints progress (steps/s, ETA) and a summary with the extremes seen; exits non-zero on the
first violation. The checks are :mod:`proprio_env.experiments.soak`'s.
"""

from __future__ import annotations

import argparse
import math
import sys

from proprio_env.experiments.soak import SoakError, soak, soak_vector
from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="proprio_env/ElbowReach-v0")
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--afferent-source", default=None)
    parser.add_argument("--backend", choices=BACKEND_CHOICES, default=DEFAULT_BACKEND,
                        help="spindle chain backend (c: compiled on first use)")
    parser.add_argument("--num-envs", type=int, default=0,
                        help="soak the vector env with this many sub-envs (0: single env)")
    parser.add_argument("--num-threads", type=int, default=1,
                        help="physics threads of the vector env")
    parser.add_argument("--report-every", type=int, default=10_000)
    parser.add_argument("--max-minutes", type=float, default=math.inf,
                        help="stop (and report the steps done) after this wall time")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error("--steps must be >= 1")
    kwargs = {"backend": args.backend}
    if args.afferent_source is not None:
        kwargs["afferent_source"] = args.afferent_source
    try:
        if args.num_envs > 0:
            result = soak_vector(args.env, args.steps, args.num_envs, args.seed,
                                 args.report_every, args.max_minutes,
                                 num_threads=args.num_threads, **kwargs)
        else:
            result = soak(args.env, args.steps, args.seed, args.report_every,
                          args.max_minutes, **kwargs)
    except SoakError as exc:
        print(f"SOAK FAILED: {exc}")
        return 1
    ex = result["extremes"]
    if result["steps"] < args.steps:
        print(f"stopped by --max-minutes after {result['steps']} of {args.steps} steps")
    print(f"{args.env}: {result['steps']} steps ({result['episodes']} episodes) in "
          f"{result['elapsed_s'] / 60:.1f} min, {result['steps_per_s']:.1f} steps/s; no "
          f"NaN/inf, state bounded: angle {ex['angle_deg'][0]:.2f}..{ex['angle_deg'][1]:.2f} "
          f"deg, Ia {ex['ia_pps'][0]:.1f}..{ex['ia_pps'][1]:.1f} pps, II "
          f"{ex['ii_pps'][0]:.1f}..{ex['ii_pps'][1]:.1f} pps; "
          f"{result['bad_actions_rejected']} bad actions rejected")
    return 0


if __name__ == "__main__":
    sys.exit(main())
