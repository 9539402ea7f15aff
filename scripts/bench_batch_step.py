"""ns per spindle step of ``ps_spindle_batch_step``: SIMD lanes against the scalar loop.

Records the inputs of every ``CSpindleBatch.step`` call (the state before it, lengths, drives)
of the C spindle bank of ``SpindleAfferentsVector`` on myo-sim's 54-muscle legs in a
``SyncVectorEnv`` of ``--envs`` envs (864 spindles at 16; 10 sub-steps of 1 ms per env step)
under random uniform controls, then replays them through ``ps_spindle_batch_step`` of three
builds of the C port compiled side by side with the same flags as the cached library
(:func:`spindle.native.build.compile_flags`):

- ``scalar``: ``-DPS_BATCH_SCALAR`` (the loop of ``ps_spindle_step_plan``, as before);
- ``lanes-sse2``: ``-DPS_LANES_NO_AVX2`` (the lanes without the AVX2 copy);
- ``lanes``: the library as shipped (AVX2 copy chosen at run time where the CPU has it).

Each round times every recorded call of each build in turn (the state reloaded before each
call, outside the timing; CPU time of this thread, so that time the shared machine gives to
other processes is not counted); the figure is the median over ``--rounds`` rounds of the ns
per spindle step. The outputs (states, Ia, II) of all builds are checked to be identical.

Last line: ``bench_batch_step scalar_ns=... lanes_ns=... ratio=... avx2=yes|no identical=yes``.

Usage: ``PYTHONPATH=. python scripts/bench_batch_step.py [--envs 16] [--steps 30]
[--rounds 7]`` (needs the ``myo`` extra).
"""

from __future__ import annotations

import argparse
import ctypes
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from spindle.native import build
from spindle.native.abi import plan_struct, structs
from spindle.native.spindle import CSpindleBatch

BUILDS = {"scalar": ("-DPS_BATCH_SCALAR",), "lanes-sse2": ("-DPS_LANES_NO_AVX2",),
          "lanes": ()}


def record(n_envs: int, steps: int, seed: int = 0) -> tuple[list, CSpindleBatch]:
    """The (state, L, gd, gs) of every CSpindleBatch.step call of the legs' vector env."""
    import gymnasium as gym
    import mujoco

    from proprio_env.wrappers import SpindleAfferentsVector
    from proprio_env.wrappers.mjcf_env import MuscleModelEnv, myo_sim_model_path

    path = myo_sim_model_path("legs_osl")
    compiled = mujoco.MjModel.from_xml_path(str(path))
    calls, batches = [], []
    original = CSpindleBatch.step

    def recording(self, length_L0, gamma_dyn_pps, gamma_stat_pps, rates=True):
        calls.append((self.fields.copy(), *(np.array(x, dtype=float) for x in
                                            (length_L0, gamma_dyn_pps, gamma_stat_pps))))
        batches.append(self)
        return original(self, length_L0, gamma_dyn_pps, gamma_stat_pps, rates)

    def one_call_per_step(self, length_L0, gamma_dyn_pps, gamma_stat_pps):
        # the bank's one call per env step, split into the sub-steps it runs
        for row in zip(length_L0, gamma_dyn_pps, gamma_stat_pps, strict=True):
            out = recording(self, *row)
        return out

    original_steps = CSpindleBatch.steps
    CSpindleBatch.step = recording
    CSpindleBatch.steps = one_call_per_step
    try:
        env = SpindleAfferentsVector(gym.vector.SyncVectorEnv(
            [lambda: MuscleModelEnv(path, frame_skip=10, model=compiled)] * n_envs),
            backend="c")
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        low, high = env.single_action_space.low, env.single_action_space.high
        for _ in range(steps):
            env.step(rng.uniform(low, high, (n_envs, low.size)).astype(np.float32))
        env.close()
    finally:
        CSpindleBatch.step = original
        CSpindleBatch.steps = original_steps
    if not calls:
        raise RuntimeError("no CSpindleBatch step was recorded")
    if len({id(b) for b in batches}) != 1:
        raise RuntimeError("expected one C spindle bank")
    return calls, batches[0]


def compile_library(extra: tuple[str, ...], directory: Path) -> ctypes.CDLL:
    out = directory / f"lib{abs(hash(extra))}.so"
    cmd = [*build.compiler_command(), *build.compile_flags("double"), *extra,
           "-I", str(build.SOURCE_DIR), *map(str, build.sources()), "-o", str(out), "-lm"]
    subprocess.run(cmd, check=True)
    return ctypes.CDLL(str(out))


class Replay:
    """One build's ps_spindle_batch_step on a copy of the recorded bank."""

    def __init__(self, lib: ctypes.CDLL, batch: CSpindleBatch) -> None:
        _, PsSpindle = structs("double")
        self.lib, self.n = lib, batch.n
        self.plan = plan_struct("double")()
        ctypes.memmove(ctypes.byref(self.plan), ctypes.byref(batch._plan),
                       ctypes.sizeof(self.plan))
        self.spindles = (PsSpindle * self.n)()
        self.backup = (PsSpindle * self.n)()
        self.fields = np.frombuffer(self.spindles, dtype=np.float64).reshape(self.n, 15)
        self.ia, self.ii = np.zeros(self.n), np.zeros(self.n)
        self.failed = ctypes.c_long()
        vp = ctypes.c_void_p
        lib.ps_spindle_batch_step.argtypes = [vp, ctypes.c_long, vp, vp, vp, vp, vp, vp, vp, vp]
        lib.ps_spindle_batch_step.restype = ctypes.c_int
        self.args = [ctypes.addressof(self.spindles), self.n, ctypes.addressof(self.plan)]
        self.tail = [ctypes.addressof(self.backup), self.ia.ctypes.data, self.ii.ctypes.data,
                     ctypes.addressof(self.failed)]

    def run(self, calls) -> tuple[float, list]:
        """(seconds in ps_spindle_batch_step over all calls, the outputs of each call)."""
        total, outputs = 0.0, []
        step = self.lib.ps_spindle_batch_step
        for state, L, gd, gs in calls:
            self.fields[...] = state
            args = [*self.args, L.ctypes.data, gd.ctypes.data, gs.ctypes.data, *self.tail]
            t = time.thread_time()
            code = step(*args)
            total += time.thread_time() - t
            if code != 0:
                raise RuntimeError(f"replayed step failed with status {code}")
            outputs.append((self.fields.copy(), self.ia.copy(), self.ii.copy()))
        return total, outputs


def cpu_has_avx2() -> bool:
    try:
        return " avx2" in Path("/proc/cpuinfo").read_text()
    except OSError:
        return False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args()
    calls, batch = record(args.envs, args.steps)
    print(f"recorded {len(calls)} calls of {batch.n} spindles "
          f"(step {batch.step_s * 1e3:g} ms, theta {batch.theta})")
    with tempfile.TemporaryDirectory() as tmp:
        replays = {name: Replay(compile_library(extra, Path(tmp)), batch)
                   for name, extra in BUILDS.items()}
        times = {name: [] for name in BUILDS}
        reference = None
        identical = True
        for _ in range(args.rounds):
            for name, replay in replays.items():
                seconds, outputs = replay.run(calls)
                times[name].append(seconds / (len(calls) * batch.n) * 1e9)
                if reference is None:
                    reference = outputs
                else:
                    identical &= all(
                        all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
                        for got, want in zip(outputs, reference, strict=True))
    ns = {name: float(np.median(t)) for name, t in times.items()}
    print(f"{'build':12s} {'median ns':>10s} {'min ns':>8s}  per spindle step "
          f"({args.rounds} rounds, shared machine)")
    for name, t in times.items():
        print(f"{name:12s} {ns[name]:10.1f} {min(t):8.1f}")
    print(f"outputs identical across builds: {identical}; CPU has AVX2: {cpu_has_avx2()} "
          f"(lanes vs lanes-sse2: {ns['lanes-sse2'] / ns['lanes']:.2f}x)")
    print(f"bench_batch_step scalar_ns={ns['scalar']:.1f} lanes_ns={ns['lanes']:.1f} "
          f"ratio={ns['scalar'] / ns['lanes']:.2f} "
          f"avx2={'yes' if cpu_has_avx2() else 'no'} identical={'yes' if identical else 'no'}")


if __name__ == "__main__":
    main()
