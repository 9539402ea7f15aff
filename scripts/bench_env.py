"""Env speed and scaling: the physics-only limit, the single envs (each chain backend) and the
native vector envs, measured side by side in one process (medians over interleaved repeats).

    python scripts/bench_env.py [--steps 2000] [--repeats 3] [--sizes 1,8,64,256,1024]
                                [--threads 1,2] [--myosuite-python PATH] [--quick]

Rates are env steps per second (for a vector env: vector steps x envs), from wall time and
from CPU time of this process. What each line measures:

- **physics-only limit**: ``mj_step`` on one ``MjData`` of the same model with random
  controls, in a tight loop on one thread, 10 per env step (the env's frame skip): what an
  env step costs with no sensing at all. Each env id has its own limit (muscles or servo).
- **single env**: ``gymnasium.make(id)`` with ``backend="numpy"``, ``"c"`` and the default
  (``"auto"``), random actions, resets at the 200-step truncation.
- **vector env**: ``gymnasium.make_vec(id, num_envs=n)`` (the native vector env) for every n
  of ``--sizes`` and every thread count of ``--threads``, numpy chain (the C chain at 64
  envs), and the peak memory per env: in a fresh process per env id and size, the peak
  resident set after building the vector env and stepping it 20 times, minus the resident
  set before building it (imports done), divided by n.
- **MyoSuite**: its 1-DoF elbow (``myoElbowPose1D6MRandom-v0``: 6 muscles, no afferents, 20 ms
  steps like ours) run by ``--myosuite-python`` (a Python with MyoSuite installed: MyoSuite
  pins gymnasium < 1.3, so it lives in its own venv) in a subprocess within the same
  interleaved repeats, or in this process when MyoSuite is importable here. Without either,
  the script says it was not measured.

Absolute figures move 2-5x between machines and with load: compare the ratios, which are
measured side by side. The last line is

    vector_env_steps_per_s=<ElbowReach-v0, 64 envs, the default backend, first --threads>
    vs_physics_limit=<that / its physics-only limit> single_env_vs_myosuite=<default
    ElbowReach-v0 / MyoSuite, steps per CPU-second, or nan when not measured>
    backend=<the default backend here: c, or numpy without a C compiler> threads=<n>
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REACH = "proprio_env/ElbowReach-v0"
PROSTHESIS = "proprio_env/ProsthesisElbow-v0"
ENV_IDS = (REACH, PROSTHESIS)
MYOSUITE_ENV_ID = "myoElbowPose1D6MRandom-v0"
"""MyoSuite's 1-DoF elbow (6 muscles, no afferents): the nearest published elbow env."""
TARGET_SIZE = 64
"""The vector-env size the last line reports (the issue's target configuration)."""


@dataclass
class Rate:
    """Env steps per wall second and per CPU second of one measurement."""

    wall: float
    cpu: float


def timed(run: Callable[[], int]) -> Rate:
    """``run()`` returns the env steps it made; their rate over its wall and CPU time."""
    wall0, cpu0 = time.perf_counter(), time.process_time()
    steps = run()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    return Rate(steps / wall, steps / max(cpu, 1e-9))


def memory_bytes(field_name: str) -> int:
    """``VmRSS`` (resident now) or ``VmHWM`` (peak resident) of this process in bytes, from
    /proc; 0 where there is none."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field_name + ":"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


MEMORY_SNIPPET = r"""
import sys
import gymnasium as gym
import proprio_env  # noqa: F401
sys.path.insert(0, sys.argv[4])
from bench_env import memory_bytes
env_id, n, backend = sys.argv[1], int(sys.argv[2]), sys.argv[3]
before = memory_bytes("VmRSS")
vec = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", backend=backend)
vec.action_space.seed(0)
vec.reset(seed=0)
for _ in range(20):
    vec.step(vec.action_space.sample())
print((memory_bytes("VmHWM") - before) / n)
"""


def peak_memory_per_env(env_id: str, n_envs: int, backend: str) -> float:
    """Peak resident bytes a vector env of ``n_envs`` adds per env, in a fresh process."""
    out = subprocess.run([sys.executable, "-c", MEMORY_SNIPPET, env_id, str(n_envs), backend,
                          str(Path(__file__).parent)], capture_output=True, text=True,
                         check=True, timeout=1800)
    return float(out.stdout.strip().splitlines()[-1])


# -- the measurements ---------------------------------------------------------------------------
def physics_limit(env_id: str, steps: int) -> Rate:
    """Env steps/s of bare physics: 10 ``mj_step`` per env step on the env's own model."""
    import gymnasium as gym
    import mujoco

    env = gym.make(env_id).unwrapped
    model, data = env.model, env.data
    frames = env.frame_skip
    env.reset(seed=0)
    low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
    ctrl = np.random.default_rng(0).uniform(low, high, (steps, model.nu))

    def run() -> int:
        for k in range(steps):
            data.ctrl[:] = ctrl[k]
            for _ in range(frames):
                mujoco.mj_step(model, data)
        return steps

    rate = timed(run)
    env.close()
    return rate


def single_env(env_id: str, steps: int, backend: str | None) -> tuple[Rate, str]:
    """(rate, backend picked) of one ``gymnasium.make`` env with random actions."""
    import gymnasium as gym

    kwargs = {} if backend is None else {"backend": backend}
    env = gym.make(env_id, **kwargs)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]
    env.reset(seed=0)

    def run() -> int:
        for a in actions:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        return steps

    rate = timed(run)
    picked = env.unwrapped.backend
    env.close()
    return rate, picked


def vector_env(env_id: str, n_envs: int, steps: int, backend: str, threads: int) -> Rate:
    """The rate of the native vector env of ``n_envs``."""
    import gymnasium as gym

    vec = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point",
                       backend=backend, num_threads=threads)
    vec.action_space.seed(0)
    n_calls = max(2, steps // n_envs)
    actions = [vec.action_space.sample() for _ in range(n_calls)]
    vec.reset(seed=0)
    vec.step(actions[0])  # buffers and caches made before the clock starts

    def run() -> int:
        for a in actions:
            vec.step(a)
        return n_calls * n_envs

    rate = timed(run)
    vec.close()
    return rate


@dataclass
class Breakdown:
    """Where one vector step's wall time goes (seconds per vector step)."""

    total: float
    physics: float
    chain: float
    spindle: float
    spindle_calls: float  # core.advance calls per vector step (sub-steps of all arms at once)

    @property
    def rest(self) -> float:
        return self.total - self.physics - self.chain


def breakdown(env_id: str, n_envs: int, steps: int, backend: str) -> Breakdown:
    """The vector env's step split into physics (``PhysicsBatch.step``: the rollout call),
    the chain (``AfferentReadout.push``: sensors, glue, spindles) and, inside it, the
    numpy spindle step (``spindle.core.advance``), by wrapping those three with timers (a
    separate run: the wrappers cost ~1 us per call)."""
    import gymnasium as gym

    import spindle.core
    from proprio_env.envs.afferents import AfferentReadout
    from proprio_env.envs.physics import PhysicsBatch

    spent = {"physics": 0.0, "chain": 0.0, "spindle": 0.0, "calls": 0}

    def timer(owner, name: str, key: str):
        original = getattr(owner, name)

        def timed_call(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                spent[key] += time.perf_counter() - t0
                if key == "spindle":
                    spent["calls"] += 1
        setattr(owner, name, timed_call)
        return original

    originals = [(PhysicsBatch, "step", timer(PhysicsBatch, "step", "physics")),
                 (AfferentReadout, "push", timer(AfferentReadout, "push", "chain")),
                 (spindle.core, "advance", timer(spindle.core, "advance", "spindle"))]
    try:
        vec = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point",
                           backend=backend)
        vec.action_space.seed(0)
        n_calls = max(2, steps // n_envs)
        actions = [vec.action_space.sample() for _ in range(n_calls)]
        vec.reset(seed=0)
        vec.step(actions[0])
        spent.update(physics=0.0, chain=0.0, spindle=0.0, calls=0)
        t0 = time.perf_counter()
        for a in actions:
            vec.step(a)
        total = time.perf_counter() - t0
        vec.close()
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)
    return Breakdown(total / n_calls, spent["physics"] / n_calls, spent["chain"] / n_calls,
                     spent["spindle"] / n_calls, spent["calls"] / n_calls)


MYOSUITE_SNIPPET = r"""
import json, sys, time
import myosuite  # noqa: F401  (registers its envs)
from myosuite.utils import gym
steps = int(sys.argv[1])
env = gym.make(sys.argv[2])
env.action_space.seed(0)
actions = [env.action_space.sample() for _ in range(steps)]
env.reset(seed=0)
wall0, cpu0 = time.perf_counter(), time.process_time()
for a in actions:
    out = env.step(a)
    if out[2] or (len(out) == 5 and out[3]):
        env.reset()
wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
print(json.dumps({"wall": steps / wall, "cpu": steps / cpu, "dt_s": float(env.unwrapped.dt),
                  "version": myosuite.__version__}))
"""


def myosuite_env(steps: int, python: str | None) -> tuple[Rate, dict] | None:
    """MyoSuite's elbow with random actions: in ``python`` (a subprocess) if given, else here
    when importable; None when neither is possible."""
    if python is None:
        try:
            import myosuite  # noqa: F401
        except ImportError:
            return None
        python = sys.executable
    out = subprocess.run([python, "-c", MYOSUITE_SNIPPET, str(steps), MYOSUITE_ENV_ID],
                         capture_output=True, text=True, check=False, timeout=1800)
    if out.returncode != 0:
        raise RuntimeError(f"MyoSuite run with {python} failed:\n{out.stderr[-2000:]}")
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    return Rate(figures["wall"], figures["cpu"]), figures


# -- the run --------------------------------------------------------------------------------------
@dataclass
class Results:
    """Every measurement of every repeat, keyed by a label."""

    rates: dict[str, list[Rate]] = field(default_factory=dict)
    memory: dict[str, list[float]] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)
    breakdowns: dict[str, list[Breakdown]] = field(default_factory=dict)

    def add(self, label: str, rate: Rate) -> None:
        self.rates.setdefault(label, []).append(rate)

    def wall(self, label: str) -> float:
        return float(np.median([r.wall for r in self.rates[label]]))

    def cpu(self, label: str) -> float:
        return float(np.median([r.cpu for r in self.rates[label]]))


def measure(args: argparse.Namespace) -> Results:
    """All measurements, repeated ``args.repeats`` times in interleaved order."""
    results = Results()
    for repeat in range(args.repeats):
        print(f"repeat {repeat + 1}/{args.repeats}", file=sys.stderr, flush=True)
        for env_id in ENV_IDS:
            results.add(f"{env_id} physics", physics_limit(env_id, args.steps))
            for backend in ("numpy", "c", None):
                rate, picked = single_env(env_id, args.steps, backend)
                label = f"{env_id} single {backend or 'default'}"
                results.add(label, rate)
                results.notes[label] = picked
            for threads in args.threads:
                for n in args.sizes:
                    label = f"{env_id} vector numpy n={n} threads={threads}"
                    results.add(label, vector_env(env_id, n, max(args.steps, 4 * n) if n > 64
                                                  else args.steps, "numpy", threads))
                    if repeat == 0 and threads == args.threads[0]:
                        results.memory[label] = [peak_memory_per_env(env_id, n, "numpy")]
            for threads in args.threads:
                results.add(f"{env_id} vector c n={TARGET_SIZE} threads={threads}",
                            vector_env(env_id, TARGET_SIZE, args.steps, "c", threads))
            for backend in ("numpy", "c"):
                results.breakdowns.setdefault(f"{env_id} {backend}", []).append(
                    breakdown(env_id, TARGET_SIZE, args.steps, backend))
        myo = myosuite_env(args.steps, args.myosuite_python)
        if myo is not None:
            results.add("myosuite", myo[0])
            results.notes["myosuite"] = (f"MyoSuite {myo[1]['version']}, "
                                         f"{1e3 * myo[1]['dt_s']:g} ms steps")
    return results


def report(results: Results, args: argparse.Namespace) -> None:
    """Print the table and the last line."""
    print(f"medians of {args.repeats} interleaved repeats of {args.steps} env steps "
          "(vector envs: at least 4 vector steps per env)")
    print(f"{'measurement':58s} {'steps/s wall':>13s} {'steps/CPU-s':>12s} "
          f"{'/ physics':>9s} {'MB/env':>7s}")
    for label in results.rates:
        env_id = label.split()[0]
        limit = results.wall(f"{env_id} physics") if env_id in ENV_IDS else math.nan
        memory = results.memory.get(label)
        mb = f"{np.median(memory) / 1e6:7.2f}" if memory else " " * 7
        note = f"  [{results.notes[label]}]" if label in results.notes else ""
        print(f"{label:58s} {results.wall(label):13.0f} {results.cpu(label):12.0f} "
              f"{results.wall(label) / limit:9.3f} {mb}{note}")
    if "myosuite" not in results.rates:
        print(f"MyoSuite {MYOSUITE_ENV_ID}: not measured (not importable here and no "
              "--myosuite-python given)")
        vs_myo = math.nan
    else:
        vs_myo = results.cpu(f"{REACH} single default") / results.cpu("myosuite")
        for env_id in ENV_IDS:
            for backend in ("default", "numpy", "c"):
                label = f"{env_id} single {backend}"
                print(f"{label} / MyoSuite (steps per CPU-second): "
                      f"{results.cpu(label) / results.cpu('myosuite'):.2f}")
    for env_id in ENV_IDS:
        limit = results.wall(f"{env_id} physics")
        for backend in ("numpy", "c"):
            for threads in args.threads:
                label = f"{env_id} vector {backend} n={TARGET_SIZE} threads={threads}"
                if label in results.rates:
                    print(f"{label} / single-thread physics limit: "
                          f"{results.wall(label) / limit:.3f}")
    report_breakdowns(results)
    # what a user gets without choosing: the default backend ("auto"), as the single env
    # picked it on this machine, in the vector env of TARGET_SIZE on the first thread count
    default = results.notes[f"{REACH} single default"]
    threads = args.threads[0]
    target = f"{REACH} vector {default} n={TARGET_SIZE} threads={threads}"
    rate = results.wall(target) if target in results.rates else math.nan
    vs_limit = rate / results.wall(f"{REACH} physics")
    myo_text = (f"{vs_myo:.2f}x MyoSuite's {MYOSUITE_ENV_ID} steps per CPU-second"
                if math.isfinite(vs_myo) else "MyoSuite not measured")
    print(f"default backend here: {default}. Single {REACH}: {myo_text}. Vector env of "
          f"{TARGET_SIZE} on {threads} thread(s): {rate:.0f} env steps/s, {vs_limit:.2f}x the "
          "single-thread physics-only limit measured beside it")
    print(f"vector_env_steps_per_s={rate:.1f} vs_physics_limit={vs_limit:.3f} "
          f"single_env_vs_myosuite={vs_myo:.3f} backend={default} threads={threads}")


TARGET_RATIO = {REACH: 0.6, PROSTHESIS: 0.4}
"""The issue's one-thread targets at TARGET_SIZE envs, numpy backend (x physics limit)."""


def report_breakdowns(results: Results) -> None:
    """Where a vector step's time goes at TARGET_SIZE envs, and the chain's budget: the time
    a vector step may take at the target ratio, minus what the physics and the rest took."""
    print(f"where a vector step's time goes, {TARGET_SIZE} envs, 1 thread (ms per vector "
          "step, medians; a separate run with timers)")
    print(f"{'':40s} {'total':>7s} {'physics':>8s} {'chain':>7s} {'spindle':>8s} "
          f"{'calls':>6s} {'us/call':>8s} {'rest':>6s} {'chain budget':>13s}")
    for key, runs in results.breakdowns.items():
        env_id = key.split()[0]
        med = {name: float(np.median([getattr(b, name) for b in runs]))
               for name in ("total", "physics", "chain", "spindle", "spindle_calls", "rest")}
        limit = results.wall(f"{env_id} physics")
        allowed = TARGET_SIZE / (TARGET_RATIO[env_id] * limit)
        budget = allowed - med["physics"] - med["rest"]
        per_call = (1e6 * med["spindle"] / med["spindle_calls"]
                    if med["spindle_calls"] else math.nan)
        print(f"{key:40s} {1e3 * med['total']:7.2f} {1e3 * med['physics']:8.2f} "
              f"{1e3 * med['chain']:7.2f} {1e3 * med['spindle']:8.2f} "
              f"{med['spindle_calls']:6.1f} {per_call:8.1f} {1e3 * med['rest']:6.2f} "
              f"{1e3 * budget:13.2f}")
    print(f"(spindle: the numpy core.advance calls inside the chain; the C chain steps its "
          f"spindles inside its own push. chain budget: what the chain may take for "
          f"{TARGET_RATIO[REACH]}x / {TARGET_RATIO[PROSTHESIS]}x the physics limit)")


def main(argv: list[str] | None = None) -> None:
    import proprio_env  # noqa: F401  (registers the envs)

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2000, help="env steps per measurement")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sizes", default="1,8,64,256,1024",
                        help="vector env sizes, comma-separated")
    parser.add_argument("--threads", default="1,2", help="thread counts, comma-separated")
    parser.add_argument("--myosuite-python", default=None,
                        help="a Python with MyoSuite installed (its own venv)")
    parser.add_argument("--quick", action="store_true",
                        help="a check that everything runs: 200 steps, 1 repeat, sizes 1,64")
    args = parser.parse_args(argv)
    if args.quick:
        args.steps, args.repeats, args.sizes = 200, 1, "1,64"
    try:
        args.sizes = sorted(int(x) for x in args.sizes.split(","))
        args.threads = [int(x) for x in args.threads.split(",")]
    except ValueError:
        parser.error("--sizes and --threads are comma-separated integers")
    if (args.steps < 1 or args.repeats < 1 or min(args.sizes) < 1
            or not set(args.threads) <= {1, 2}):
        parser.error("--steps, --repeats and sizes must be >= 1; threads 1 or 2")
    if TARGET_SIZE not in args.sizes:
        args.sizes = sorted({*args.sizes, TARGET_SIZE})
    report(measure(args), args)


if __name__ == "__main__":
    main()
