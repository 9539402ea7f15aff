"""Env speed of this tree against another checkout, side by side; not a timed test.

    python scripts/bench_revisions.py --old /tmp/oldmain [--old-cache /tmp/pcache-old]
        [--repeats 5] [--steps 2000] [--only single,vector] [--valgrind]

Each measurement runs in a fresh subprocess of this Python, alternately in this tree and in
``--old`` (``PYTHONPATH`` and the working directory set to the tree, ``PROPRIO_C_CACHE`` to
each tree's own build cache), so machine load hits both alike; the figures are medians over
the repeats and the ratio is new / old (above 1: this tree is faster). Measured:

- **single**: ``gymnasium.make(id, backend=b)`` for ElbowReach-v0 and ProsthesisElbow-v0,
  ``b`` in c and numpy: random actions, resets at the 200-step truncation, env steps per
  second of CPU time of the subprocess (and of wall time); ``--steps`` steps with numpy, 5x
  as many with C;
- **vector**: ``gymnasium.make_vec(id, num_envs=64)`` with the default backend on one thread:
  env steps (vector steps x 64) per CPU second;
- **valgrind** (``--valgrind``): instructions per single-env step (backend c, resets
  included), counted by callgrind inside the loop of ``--valgrind-steps`` steps only
  (``--toggle-collect`` on the ``functools.reduce`` that runs it: no imports, set-up or action
  sampling): deterministic, the witness when the machine is loaded. The ratio is old / new
  instructions (above 1: this tree does less work).

The last line is ``ratios <label>=<ratio> ...`` for every measurement: new / old rates and
old / new instructions, so above 1 this tree is the better one in each.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
ENV_IDS = ("ElbowReach-v0", "ProsthesisElbow-v0")
VECTOR_SIZE = 64

# Self-contained rather than importing bench_env: it must run unchanged in the other
# checkout, whose scripts (and private APIs) may differ from this tree's.
SNIPPET = r"""
import json, sys, time
import numpy as np
import gymnasium as gym
import proprio_env  # noqa: F401  (registers the envs)
kind, env_id, backend = sys.argv[1], "proprio_env/" + sys.argv[2], sys.argv[3]
steps = int(sys.argv[4])
kwargs = {} if backend == "default" else {"backend": backend}
if kind == "single":
    env = gym.make(env_id, **kwargs)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]
    env.reset(seed=0)
    for a in actions[:50]:  # caches and lazy builds before the clock starts
        env.step(a)
    env.reset(seed=0)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    n = steps
else:
    n_envs = int(sys.argv[5])
    env = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point",
                       num_threads=1, **kwargs)
    env.action_space.seed(0)
    calls = max(2, steps // n_envs)
    actions = [env.action_space.sample() for _ in range(calls)]
    env.reset(seed=0)
    env.step(actions[0])
    wall0, cpu0 = time.perf_counter(), time.process_time()
    for a in actions:
        env.step(a)
    n = calls * n_envs
wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
picked = env.unwrapped.backend if kind == "single" else env.backend
env.close()
print(json.dumps({"wall": n / wall, "cpu": n / cpu, "backend": picked}))
"""

VALGRIND_SNIPPET = r"""
import functools, sys
import gymnasium as gym
import proprio_env  # noqa: F401
env_id, backend, steps = "proprio_env/" + sys.argv[1], sys.argv[2], int(sys.argv[3])
env = gym.make(env_id, backend=backend)
env.action_space.seed(0)
actions = [env.action_space.sample() for _ in range(steps)]
env.reset(seed=0)
for a in actions[:5]:
    env.step(a)
env.reset(seed=0)

def step(acc, a):
    _, _, terminated, truncated, _ = env.step(a)
    if terminated or truncated:
        env.reset()
    return acc

# callgrind counts only inside functools.reduce (--toggle-collect): the steps and resets
functools.reduce(step, actions, None)
env.close()
"""


def tree_env(tree: Path, cache: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(tree), PROPRIO_C_CACHE=cache, PYTHONHASHSEED="0",
               OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    return env


def run_once(tree: Path, cache: str, args: list[str]) -> dict:
    out = subprocess.run([sys.executable, "-c", SNIPPET, *args], cwd=tree,
                         env=tree_env(tree, cache), capture_output=True, text=True,
                         timeout=1800, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"{args} in {tree} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def instructions(tree: Path, cache: str, env_id: str, backend: str, steps: int) -> float:
    """Instructions per single-env step (resets at the 200-step truncation included), as
    callgrind counts them inside the loop of ``steps`` steps only."""
    with tempfile.TemporaryDirectory() as tmp:
        out_file = Path(tmp) / "callgrind.out"
        run = subprocess.run(
            ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out_file}",
             "--collect-atstart=no", "--toggle-collect=functools_reduce",
             sys.executable, "-c", VALGRIND_SNIPPET, env_id, backend, str(steps)],
            cwd=tree, env=tree_env(tree, cache), capture_output=True, text=True,
            timeout=3600, check=False)
        if run.returncode != 0:
            raise RuntimeError(f"valgrind in {tree} failed:\n{run.stderr[-3000:]}")
        text = out_file.read_text(errors="replace")
    match = re.search(r"^(?:summary|totals):\s+(\d+)", text, re.MULTILINE)
    if match is None:
        raise RuntimeError("no instruction total in callgrind's output")
    return int(match.group(1)) / steps


def measurements(only: set[str], steps: int) -> dict[str, list[str]]:
    """label -> the snippet's arguments."""
    out: dict[str, list[str]] = {}
    if "single" in only:
        for env_id in ENV_IDS:
            for backend in ("c", "numpy"):
                # the C env steps ~15x faster: 5x the steps keep its run above a CPU-second
                n = 5 * steps if backend == "c" else steps
                out[f"{env_id} single {backend}"] = ["single", env_id, backend, str(n)]
    if "vector" in only:
        for env_id in ENV_IDS:
            out[f"{env_id} vector default n={VECTOR_SIZE}"] = [
                "vector", env_id, "default", str(max(steps, 8 * VECTOR_SIZE)),
                str(VECTOR_SIZE)]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", required=True, type=Path, help="the other checkout")
    parser.add_argument("--old-cache", default="/tmp/pcache-old",
                        help="PROPRIO_C_CACHE for the other checkout")
    parser.add_argument("--cache", default=os.environ.get("PROPRIO_C_CACHE",
                                                          "/tmp/pcache-bench-new"),
                        help="PROPRIO_C_CACHE for this tree")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--only", default="single,vector",
                        help="comma-separated: single, vector (and --valgrind)")
    parser.add_argument("--valgrind", action="store_true",
                        help="also count instructions per single C env step")
    parser.add_argument("--valgrind-steps", type=int, default=400)
    args = parser.parse_args(argv)
    trees = {"new": (HERE, args.cache), "old": (args.old.resolve(), args.old_cache)}
    todo = measurements(set(args.only.split(",")), args.steps)
    rates: dict[str, dict[str, list[dict]]] = {label: {"new": [], "old": []} for label in todo}
    for repeat in range(args.repeats):
        print(f"repeat {repeat + 1}/{args.repeats}", file=sys.stderr, flush=True)
        order = ("new", "old") if repeat % 2 == 0 else ("old", "new")
        for label, snippet_args in todo.items():
            for side in order:
                rates[label][side].append(run_once(*trees[side], snippet_args))
    ratios: dict[str, float] = {}
    print(f"new: {HERE}  old: {trees['old'][0]}; medians of {args.repeats} alternating "
          f"repeats, fresh subprocess each, {args.steps} env steps ({5 * args.steps} with a "
          "single C env)")
    print(f"{'measurement':42s} {'new CPU':>9s} {'old CPU':>9s} {'ratio':>6s} "
          f"{'new wall':>9s} {'old wall':>9s} {'ratio':>6s}  backend")
    for label, sides in rates.items():
        med = {side: {key: statistics.median(r[key] for r in runs) for key in ("cpu", "wall")}
               for side, runs in sides.items()}
        cpu = med["new"]["cpu"] / med["old"]["cpu"]
        wall = med["new"]["wall"] / med["old"]["wall"]
        ratios[label.replace(" ", "_")] = cpu
        print(f"{label:42s} {med['new']['cpu']:9.0f} {med['old']['cpu']:9.0f} {cpu:6.3f} "
              f"{med['new']['wall']:9.0f} {med['old']['wall']:9.0f} {wall:6.3f}  "
              f"{sides['new'][0]['backend']}/{sides['old'][0]['backend']}")
    if args.valgrind:
        for env_id in ENV_IDS:
            per_step = {side: instructions(tree, cache, env_id, "c", args.valgrind_steps)
                        for side, (tree, cache) in trees.items()}
            ratio = per_step["old"] / per_step["new"]
            ratios[f"{env_id}_single_c_instructions"] = ratio
            print(f"{env_id} single c: {per_step['new']:,.0f} instructions per step here, "
                  f"{per_step['old']:,.0f} old: old/new {ratio:.3f} (callgrind, "
                  f"{args.valgrind_steps} steps)")
    print("ratios " + " ".join(f"{k}={v:.3f}" for k, v in ratios.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
