"""Fault-injection soak of the arm chain: numpy and C backends fed the same faulty stream.

    python scripts/fault_soak.py                 # 10^6 samples (numpy dominates the time)
    python scripts/fault_soak.py --quick         # ~10^4 samples
    python scripts/fault_soak.py --samples 200000 --seed 3 --no-progress
    python scripts/fault_soak.py --samples 0 --wrapper-steps 5000   # the wrappers only

The stream, the faults and the checks are those of
:mod:`proprio_env.experiments.fault_injection` (servo moves read by a noisy AX-12 encoder,
with the servo's load word beside each reading; dropouts from one sample to minutes, clock
jumps, corrupted times, readings and load words, readings without load). Prints a summary
table, then a last line
``fault_soak samples=<n> counters_equal=<bool> max_rate_diff_pps=<f> max_ib_diff_pps=<f>
rss_growth_MB=<f> nonfinite=<n> ...``; exits 1 if any check fails.

Then the wrapper section (:mod:`proprio_env.experiments.wrapper_fault_injection`):
``--wrapper-steps`` wrapped steps per target (single, single lagged, vector with SAME_STEP
autoreset) and backend, with clock jumps, copies and refused actions between steps; its table
and a line
``wrapper_soak steps=<n> ... ok=<bool>`` come before the chain's last line; then the
vector-env section (:mod:`proprio_env.experiments.vector_fault_injection`, ``--vector-steps``):
native vector envs of both ids beside a twin, refused resets with bad seeds and options
between steps, a line ``vector_soak ... ok=<bool>`` per id.
"""

from __future__ import annotations

import argparse
import sys

from proprio_env.experiments.fault_injection import run_soak
from proprio_env.experiments.vector_fault_injection import run_vector_soak
from proprio_env.experiments.wrapper_fault_injection import run_wrapper_soak


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_000_000,
                        help="samples to push (default 10^6)")
    parser.add_argument("--quick", action="store_true", help="10^4 samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-call-s", type=float, default=5.0,
                        help="stop (and count) a push call running longer than this (s)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--wrapper-steps", type=int, default=None,
                        help="wrapped steps per wrapper target and backend (default 2000, "
                             "--quick 200; 0: no wrapper section)")
    parser.add_argument("--vector-steps", type=int, default=None,
                        help="vector-env steps per env id with refused resets between them "
                             "(default 2000, --quick 200; 0: no vector-env section)")
    args = parser.parse_args(argv)
    n = 10_000 if args.quick else args.samples
    wrapper_steps = (200 if args.quick else 2000) if args.wrapper_steps is None \
        else args.wrapper_steps
    vector_steps = (200 if args.quick else 2000) if args.vector_steps is None \
        else args.vector_steps
    if n < 0 or wrapper_steps < 0 or vector_steps < 0 or n + wrapper_steps + vector_steps < 1:
        parser.error(f"--samples={n}, --wrapper-steps={wrapper_steps} and --vector-steps="
                     f"{vector_steps} must be >= 0, not all 0")
    wrappers = (run_wrapper_soak(wrapper_steps, seed=args.seed, max_call_s=args.max_call_s)
                if wrapper_steps else None)
    vectors = run_vector_soak(vector_steps, seed=args.seed) if vector_steps else {}
    sections_ok = (wrappers is None or wrappers.ok) and all(r.ok for r in vectors.values())
    if n == 0:
        _print_sections(wrappers, vectors)
        return 0 if sections_ok else 1

    bar = None
    if not args.no_progress:
        from tqdm import tqdm

        bar = tqdm(total=n, unit="sample", unit_scale=True, file=sys.stderr)
    try:
        report = run_soak(n, seed=args.seed, max_call_s=args.max_call_s,
                          progress=None if bar is None else bar.update)
    finally:
        if bar is not None:
            bar.close()
    print(report.table())
    _print_sections(wrappers, vectors)
    print(report.last_line())
    return 0 if report.ok and sections_ok else 1


def _print_sections(wrappers, vectors) -> None:
    if wrappers is not None:
        print(wrappers.table())
        print(wrappers.last_line())
    for env_id, vector in vectors.items():
        print(f"{env_id}: refused resets {vector.refused}")
        print(vector.last_line())


if __name__ == "__main__":
    sys.exit(main())
