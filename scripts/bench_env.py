"""Env speed: steps/s of one env and of an 8-env vector, against raw ``mj_step`` on the same
model, measured side by side in one run (medians over interleaved repeats).

The chain backend is ``"c"`` when ``spindle.chain.BACKENDS`` has it, else ``"numpy"`` (the
script says which). When MyoSuite is importable, its 1-DoF elbow env (no afferents,
``myoElbowPose1D6MRandom-v0``) is measured in the same interleaved repeats and the ratio
printed; otherwise the script says it was not measured. Absolute steps/s move 2-5x between
machines: compare ratios measured in one run.

    python scripts/bench_env.py [--steps 2000] [--repeats 3] [--backend c|numpy]

The last line is ``env_steps_per_s=<float> vs_raw_mj_step=<float>``: one ElbowReach-v0 env
(default settings, 20 ms steps, random actions, resets every 200 steps) and its ratio to raw
``mj_step`` calls per second (each env step runs 10 of them).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def bench_raw(steps: int) -> float:
    """Raw ``mj_step``/s on the muscle-driven elbow with random excitations."""
    import mujoco

    from proprio_env.envs.base import SERVO_GROUP_BIT
    from proprio_env.model import load_model

    model = load_model()
    model.opt.disableactuator = SERVO_GROUP_BIT
    data = mujoco.MjData(model)
    ctrl = np.random.default_rng(0).uniform(0, 1, (steps, model.nu))
    start = time.perf_counter()
    for k in range(steps):
        data.ctrl[:] = ctrl[k]
        mujoco.mj_step(model, data)
    return steps / (time.perf_counter() - start)


def bench_env(env_id: str, steps: int, backend: str) -> tuple[float, float]:
    """(env steps/s of one ``gymnasium.make`` env, share of the time in the spindle chain)."""
    import gymnasium as gym

    env = gym.make(env_id, backend=backend)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]
    readout = env.unwrapped.afferents
    push = readout.push
    chain_s = [0.0]

    def timed_push(*args):
        t0 = time.perf_counter()
        out = push(*args)
        chain_s[0] += time.perf_counter() - t0
        return out

    readout.push = timed_push
    env.reset(seed=0)
    start = time.perf_counter()
    for a in actions:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return steps / elapsed, chain_s[0] / elapsed


MYOSUITE_ENV_ID = "myoElbowPose1D6MRandom-v0"
"""MyoSuite's 1-DoF elbow (6 muscles, no afferents): the nearest published elbow env."""


def bench_myosuite(steps: int) -> tuple[float, float] | None:
    """(env steps/s, env step in s) of MyoSuite's 1-DoF elbow with random actions, resetting
    when an episode ends; None when MyoSuite is not importable."""
    try:
        import myosuite  # noqa: F401  (registers its envs)
        from myosuite.utils import gym as myo_gym
    except ImportError:
        return None
    env = myo_gym.make(MYOSUITE_ENV_ID)
    env.action_space.seed(0)
    actions = [env.action_space.sample() for _ in range(steps)]
    env.reset(seed=0)
    start = time.perf_counter()
    for a in actions:
        out = env.step(a)  # gymnasium's 5-tuple, or old gym's 4-tuple
        if out[2] or (len(out) == 5 and out[3]):
            env.reset()
    elapsed = time.perf_counter() - start
    dt_s = float(env.unwrapped.dt)
    env.close()
    return steps / elapsed, dt_s


def bench_vector(env_id: str, n_envs: int, steps: int, backend: str) -> float:
    """Env steps/s (summed over the envs) of a ``SyncVectorEnv`` of ``n_envs``."""
    import gymnasium as gym

    vec = gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="sync",
                       backend=backend)
    vec.action_space.seed(0)
    n_calls = max(1, steps // n_envs)
    actions = [vec.action_space.sample() for _ in range(n_calls)]
    vec.reset(seed=0)
    start = time.perf_counter()
    for a in actions:
        vec.step(a)
    elapsed = time.perf_counter() - start
    vec.close()
    return n_calls * n_envs / elapsed


def main(argv: list[str] | None = None) -> None:
    import proprio_env  # noqa: F401  (registers the envs)
    from spindle.chain import BACKENDS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="env steps per measurement")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backend", default=None, help="chain backend (default: c if built)")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.repeats < 1:
        parser.error("--steps and --repeats must be >= 1")
    backend = args.backend or ("c" if "c" in BACKENDS else "numpy")
    note = "" if "c" in BACKENDS else " (the C backend is not available in this build)"
    print(f"chain backend: {backend}{note}; available: {BACKENDS}")

    reach, prosthesis, vector, raw, myo = [], [], [], [], []
    reach_share, prosthesis_share = [], []
    for _ in range(args.repeats):
        raw.append(bench_raw(10 * args.steps))
        rate, share = bench_env("proprio_env/ElbowReach-v0", args.steps, backend)
        reach.append(rate)
        reach_share.append(share)
        rate, share = bench_env("proprio_env/ProsthesisElbow-v0", args.steps, backend)
        prosthesis.append(rate)
        prosthesis_share.append(share)
        vector.append(bench_vector("proprio_env/ElbowReach-v0", 8, args.steps, backend))
        myo.append(bench_myosuite(args.steps))
    med = {k: float(np.median(v)) for k, v in (("reach", reach), ("prosthesis", prosthesis),
                                               ("vector", vector), ("raw", raw),
                                               ("reach_share", reach_share),
                                               ("prosthesis_share", prosthesis_share))}
    print(f"raw mj_step/s (same model)           : {med['raw']:10.0f}  "
          f"(physics-only ceiling at 10 mj_step per env step: {med['raw'] / 10:.0f} env steps/s)")
    print(f"ElbowReach-v0, 1 env (exact lengths)  : {med['reach']:10.1f} env steps/s, "
          f"{100 * med['reach_share']:.0f} % of it in the spindle chain")
    print(f"ProsthesisElbow-v0, 1 env (encoder)   : {med['prosthesis']:10.1f} env steps/s, "
          f"{100 * med['prosthesis_share']:.0f} % of it in the spindle chain")
    print(f"ElbowReach-v0, SyncVectorEnv of 8     : {med['vector']:10.1f} env steps/s (total)")
    print(f"medians of {args.repeats} interleaved repeats of {args.steps} env steps")
    if myo[0] is None:
        print(f"MyoSuite {MYOSUITE_ENV_ID}: not measured (myosuite is not importable)")
    else:
        myo_rate = float(np.median([rate for rate, _ in myo]))
        print(f"MyoSuite {MYOSUITE_ENV_ID} (no afferents, {1e3 * myo[0][1]:g} ms steps): "
              f"{myo_rate:.1f} env steps/s; ElbowReach-v0 / MyoSuite = "
              f"{med['reach'] / myo_rate:.2f}")
    print(f"env_steps_per_s={med['reach']:.1f} vs_raw_mj_step={med['reach'] / med['raw']:.5f}")


if __name__ == "__main__":
    main()
