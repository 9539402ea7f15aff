"""Cost of the spindle-afferent wrapper per muscle per env step, and against the physics.

For myo-sim's 6-muscle elbow and 54-muscle legs (``MuscleModelEnv``, 10 physics steps per
env step), single env and a ``SyncVectorEnv`` of ``--envs`` envs: the bare env and the
wrapped env step the same random actions, alternately in ``--repeats`` rounds (CPU time,
median). The wrapper's cost is the difference; the physics is ``mj_step`` x 10 on the same
model in the same run. The numpy core is the only one that runs many independent spindles
per call (the C core steps one spindle per call: ``spindle.native.spindle``).

Also: the lengths of the Hermite fallback against the recorded physics steps on this
project's elbow during a fast bang-bang movement.

Last line: ``bench_wrapper legs_vec_numpy_vs_physics=... legs_single_numpy_vs_physics=...
elbow_vec_numpy_vs_physics=... hermite_max_length_error_L0=...``.

Usage: ``PYTHONPATH=. python scripts/bench_wrapper.py [--envs 16] [--steps 40]
[--repeats 3]`` (needs the ``myo`` extra); ``--figure docs/img/wrapper_legs_afferents.png``
draws the docs figure instead.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import mujoco
import numpy as np

from proprio_env.model import MUSCLES, model_path
from proprio_env.wrappers import SpindleAfferents, SpindleAfferentsVector
from proprio_env.wrappers.capture import hermite_knots
from proprio_env.wrappers.mjcf_env import MuscleModelEnv, myo_sim_model_path
from proprio_env.wrappers.muscles import ActuatorKinematics, find_muscles

FRAME_SKIP = 10


def physics_step_s(path, repeats: int = 3, steps: int = 300) -> float:
    """CPU seconds of one mj_step under random controls (median of ``repeats``)."""
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    times = []
    for _ in range(repeats):
        mujoco.mj_resetData(model, data)
        if model.nkey:
            mujoco.mj_resetDataKeyframe(model, data, 0)
        controls = rng.uniform(0, 1, (steps, model.nu))
        t = time.process_time()
        for u in controls:
            data.ctrl[:] = u
            mujoco.mj_step(model, data)
        times.append((time.process_time() - t) / steps)
    return float(np.median(times))


def env_step_s(env, actions) -> float:
    env.reset(seed=0)
    t = time.process_time()
    for a in actions:
        env.step(a)
    return (time.process_time() - t) / len(actions)


def compare(make_bare, make_wrapped, actions, repeats: int) -> tuple[float, float]:
    """Median CPU seconds per step of the bare and the wrapped env, measured alternately."""
    bare, wrapped = make_bare(), make_wrapped()
    b, w = [], []
    for r in range(repeats):
        pair = [(bare, b), (wrapped, w)]
        for env, out in (pair if r % 2 == 0 else pair[::-1]):
            out.append(env_step_s(env, actions))
    return float(np.median(b)), float(np.median(w))


def hermite_error_L0(steps: int = 150) -> float:
    """Largest |Hermite curve - recorded length| (L0) at the physics steps of the elbow
    under bang-bang muscle drive (reversals every 3 or 10 env steps, hitting the joint
    limits at up to ~5 L0/s)."""
    model = mujoco.MjModel.from_xml_path(str(model_path()))
    model.opt.disableactuator = 1 << 2  # the position servo
    data = mujoco.MjData(model)
    muscles = find_muscles(model, list(MUSCLES))
    kin = ActuatorKinematics(model, muscles.ids)
    worst = 0.0
    for period in (3, 10):
        mujoco.mj_resetData(model, data)
        data.qpos[0] = 1.0
        mujoco.mj_forward(model, data)
        for i in range(steps):
            data.ctrl[:2] = (1.0, 0.0) if (i // period) % 2 == 0 else (0.0, 1.0)
            t0 = data.time
            length, velocity = kin.of_data(data)
            L0, V0 = muscles.length_L0(length), muscles.velocity_L0_s(velocity)
            frames = []
            for _ in range(FRAME_SKIP):
                mujoco.mj_step(model, data)
                frames.append(muscles.length_L0(kin.of_data(data)[0]))
            length, velocity = kin.of_data(data)
            _, curve, _ = hermite_knots(
                np.array([t0]), L0[None], V0[None], np.array([data.time]),
                muscles.length_L0(length)[None], muscles.velocity_L0_s(velocity)[None],
                FRAME_SKIP)
            worst = max(worst, float(np.abs(curve[:, 0] - np.array(frames)).max()))
    return worst


def figure(path: str) -> None:
    """docs/img/wrapper_legs_afferents.png: lengths, Ia and II of four left-leg muscles of
    myo-sim's legs under random controls on 30 % of the actuators, held 0.1 s."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    env = SpindleAfferents(MuscleModelEnv(myo_sim_model_path("legs_osl"), frame_skip=10))
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    names = env.muscle_names
    pick = [names.index(n) for n in ("vasmed_l", "recfem_l", "gasmed_l", "tibant_l")]
    shape = env.action_space.shape
    t, ia, ii, length = [], [], [], []
    for i in range(150):
        if i % 10 == 0:
            u = (rng.uniform(0, 1, shape) * (rng.uniform(size=shape) < 0.3)).astype(np.float32)
        _, _, _, _, info = env.step(u)
        t.append(env.unwrapped.data.time)
        ia.append(info["spindle_ia_pps"][pick])
        ii.append(info["spindle_ii_pps"][pick])
        length.append(info["spindle_measured_length_L0"][pick])
    fig, ax = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for j, k in enumerate(pick):
        ax[0].plot(t, np.array(length)[:, j], label=names[k])
        ax[1].plot(t, np.array(ia)[:, j])
        ax[2].plot(t, np.array(ii)[:, j])
    ax[0].axhspan(0.5, 1.5, color="0.93", zorder=-1)
    ax[0].set_ylabel("length (L0,\nMuJoCo normalised)")
    ax[1].set_ylabel("Ia (pps)")
    ax[2].set_ylabel("II (pps)")
    ax[2].set_xlabel("time (s)")
    ax[0].legend(ncol=4, fontsize=8)
    ax[0].set_title("myo-sim legs + OSL, random muscle controls held 0.1 s "
                    "(SpindleAfferents, constant drive 85/100 pps)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--steps", type=int, default=40, help="env steps per measurement")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--figure", metavar="PNG",
                        help="only draw the docs figure (needs matplotlib) to this path")
    args = parser.parse_args()
    if args.figure:
        figure(args.figure)
        return
    rng = np.random.default_rng(0)
    ratios = {}
    print(f"{'model':10s} {'mode':8s} {'muscles':>7s} {'bare ms':>9s} {'wrapped ms':>10s} "
          f"{'+ms/step':>9s} {'us/muscle':>9s} {'physics ms':>10s} {'x physics':>9s}")
    for name in ("elbow", "legs_osl"):
        path = myo_sim_model_path(name)
        physics = physics_step_s(path, args.repeats) * FRAME_SKIP  # one env's physics

        def bare(path=path):
            return MuscleModelEnv(path, frame_skip=FRAME_SKIP)

        n_muscles = len(find_muscles(bare().model).names)
        probe = bare()
        single = [probe.action_space.sample() for _ in range(args.steps)]
        b, w = compare(bare, lambda bare=bare: SpindleAfferents(bare()), single, args.repeats)
        rows = [("single", 1, b, w)]
        n = args.envs
        batch = [rng.uniform(probe.action_space.low, probe.action_space.high,
                             (n, probe.action_space.shape[0])).astype(np.float32)
                 for _ in range(max(4, args.steps // 4))]
        b, w = compare(lambda bare=bare, n=n: gym.vector.SyncVectorEnv([bare] * n),
                       lambda bare=bare, n=n: SpindleAfferentsVector(
                           gym.vector.SyncVectorEnv([bare] * n)), batch, args.repeats)
        rows.append((f"vec{n}", n, b, w))
        for mode, n_envs, b, w in rows:
            added = w - b
            ratio = added / (physics * n_envs)
            ratios[f"{name}_{'vec' if n_envs > 1 else 'single'}"] = ratio
            print(f"{name:10s} {mode:8s} {n_muscles * n_envs:7d} {b * 1e3:9.3f} {w * 1e3:10.3f} "
                  f"{added * 1e3:9.3f} {added / (n_muscles * n_envs) * 1e6:9.2f} "
                  f"{physics * n_envs * 1e3:10.3f} {ratio:9.3f}")
    print("C core: none runs many independent spindles per call (spindle.native.spindle "
          "steps one spindle per ctypes call), so no C column")
    error = hermite_error_L0()
    print(f"Hermite fallback vs recorded physics steps, elbow, bang-bang: max |dL| = "
          f"{error:.4f} L0")
    print(f"bench_wrapper legs_vec_numpy_vs_physics={ratios['legs_osl_vec']:.3f} "
          f"legs_single_numpy_vs_physics={ratios['legs_osl_single']:.3f} "
          f"elbow_vec_numpy_vs_physics={ratios['elbow_vec']:.3f} "
          f"hermite_max_length_error_L0={error:.4f}")


if __name__ == "__main__":
    main()
