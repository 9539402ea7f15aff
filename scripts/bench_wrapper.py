"""Cost of the spindle-afferent wrapper per muscle per env step, and against the physics.

For myo-sim's 6-muscle elbow and 54-muscle legs (``MuscleModelEnv``, 10 physics steps per
env step), single env and ``SyncVectorEnv`` of 16 and 64 envs (``--envs``), numpy and C
spindle backends, each with the afferents of the env's state now and lagging one physics step
(``lag_physics_step``, no end-of-step kinematics; ``--lag``), side by side: the bare env and
the wrapped envs step the same random actions side by side, each action in turn by every env
(CPU time per step, ``--repeats`` passes). The wrapper's cost is the difference; "x" divides
it by the bare env's own step on the same action (physics plus Gymnasium's own work) and takes
the median over steps.

Also: the lengths of the Hermite fallback against the recorded physics steps on this
project's elbow during a fast bang-bang movement.

Last line: ``bench_wrapper legs_vector16_numpy_vs_physics=... legs_vector16_c_lag_vs_physics=...``
and the same for the other rows. Targets (legs, >= 16 envs): numpy <= 0.3, C <= 0.1.

``--myosuite-python PATH``: also run MyoSuite envs (their own venv: MyoSuite pins gymnasium
< 1.3) bare and wrapped in a subprocess of that interpreter with this repository on
``PYTHONPATH``, side by side (``--myosuite-envs``).

Usage: ``PYTHONPATH=. python scripts/bench_wrapper.py [--envs 16 64] [--steps 40]
[--repeats 3] [--myosuite-python /work/myovenv/bin/python]`` (needs the ``myo`` extra);
``--figure docs/img/wrapper_legs_afferents.png`` draws the docs figure instead;
``--breakdown 16 [--steps 40 --repeats 3]`` prints where the time of a wrapped legs vector step
of 16 envs goes (C, lagging, unless ``--backends`` / ``--lag`` say otherwise);
``--instructions --steps 20 --lag 0`` counts the instructions per env step of the bare and
the wrapped single legs env under valgrind's callgrind (exact, whatever the machine's load;
needs valgrind): last line ``bench_wrapper_instructions bare=... wrapped=... ratio=...``.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import mujoco
import numpy as np

from proprio_env.body.model import MUSCLES, model_path
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


def compare(make_bare, makers: dict, actions, repeats: int) -> tuple[float, dict, dict]:
    """CPU seconds per step of the bare env and of each wrapped env, stepped side by side: the
    envs take each action in turn (the order rotating from action to action), ``repeats``
    passes over ``actions`` from the same reset. Returns the bare env's median step, each
    wrapped env's median step, and the median over steps of each wrapped env's added time over
    the bare env's on the same action (the same physics state, a few milliseconds apart: the
    load of a shared machine drifts little in between)."""
    envs = {"bare": make_bare(), **{k: m() for k, m in makers.items()}}
    names = list(envs)
    times: dict[str, list[float]] = {k: [] for k in envs}
    for _ in range(repeats):
        for env in envs.values():
            env.reset(seed=0)
        for i, action in enumerate(actions):
            for k in names[i % len(names):] + names[:i % len(names)]:
                t = time.process_time()
                envs[k].step(action)
                times[k].append(time.process_time() - t)
    for env in envs.values():
        env.close()
    bare = np.array(times.pop("bare"))
    return (float(np.median(bare)), {k: float(np.median(v)) for k, v in times.items()},
            {k: float(np.median((np.array(v) - bare) / bare)) for k, v in times.items()})


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


def bench_rows(name: str, args, backends: tuple[str, ...], ratios: dict) -> None:
    """Print the rows of one model: single env and each vector size, every backend."""
    path = myo_sim_model_path(name)
    rng = np.random.default_rng(0)
    compiled = mujoco.MjModel.from_xml_path(str(path))

    def bare(path=path):
        # a copy of the model compiled once: compiling the legs per env costs ~0.6 s, most of
        # it system time (outside the timed steps, but it was most of this script's run)
        return MuscleModelEnv(path, frame_skip=FRAME_SKIP, model=compiled)

    probe = bare()
    n_muscles = len(find_muscles(probe.model).names)
    physics = physics_step_s(path, args.repeats) * FRAME_SKIP
    low, high = probe.action_space.low, probe.action_space.high
    setups = [("single", 1)] + [(f"vector{n}", n) for n in args.envs]
    variants = [(b, lag) for b in backends for lag in args.lag]
    for mode, n in setups:
        if n == 1:
            actions = [probe.action_space.sample() for _ in range(args.steps)]
            make_bare = bare
            makers = {variant_name(b, lag): (lambda b=b, lag=lag: SpindleAfferents(
                bare(), backend=b, lag_physics_step=lag)) for b, lag in variants}
        else:
            actions = [rng.uniform(low, high, (n, low.size)).astype(np.float32)
                       for _ in range(max(4, args.steps // 4))]

            def make_bare(n=n):
                return gym.vector.SyncVectorEnv([bare] * n)

            makers = {variant_name(b, lag): (lambda b=b, n=n, lag=lag: SpindleAfferentsVector(
                gym.vector.SyncVectorEnv([bare] * n), backend=b, lag_physics_step=lag))
                for b, lag in variants}
        b, wrapped, round_ratios = compare(make_bare, makers, actions, args.repeats)
        cells = []
        for key in makers:
            added = wrapped[key] - b
            ratio = round_ratios[key]
            ratios[f"{'legs' if name == 'legs_osl' else name}_{mode}_{key}_vs_physics"] = ratio
            cells.append(f"{added / (n_muscles * n) * 1e6:9.2f} {ratio:7.3f}")
        print(f"{name:9s} {mode:9s} {n_muscles * n:7d} {b * 1e3:9.3f} "
              f"{physics * n * 1e3:10.3f} " + " ".join(cells))


def variant_name(backend: str, lag: bool) -> str:
    return f"{backend}_lag" if lag else backend


def breakdown(n_envs: int, backend: str, lag: bool, steps: int, repeats: int) -> None:
    """Where the added time of one wrapped legs vector step goes: CPU time per vector step of
    the bare vector env, of the wrapped env's inner vector step (physics, Gymnasium and the
    recording of every physics step) and of the wrapper's own parts, stepped side by side."""
    import proprio_env.wrappers.vector as vector_module

    path = myo_sim_model_path("legs_osl")
    compiled = mujoco.MjModel.from_xml_path(str(path))

    def make():
        return MuscleModelEnv(path, frame_skip=FRAME_SKIP, model=compiled)

    bare = gym.vector.SyncVectorEnv([make] * n_envs)
    wrapped = SpindleAfferentsVector(gym.vector.SyncVectorEnv([make] * n_envs),
                                     backend=backend, lag_physics_step=lag)
    spent: dict[str, float] = {}

    def timed(name, fn):
        def run(*args, **kwargs):
            t = time.process_time()
            out = fn(*args, **kwargs)
            spent[name] = spent.get(name, 0.0) + time.process_time() - t
            return out
        return run

    wrapped.env.step = timed("inner vector step (physics + recording)", wrapped.env.step)
    wrapped.bank._integrate = timed("spindle sub-steps", wrapped.bank._integrate)
    wrapped.bank.advance = timed("bank (rules, sub-step lengths) + spindle sub-steps",
                                 wrapped.bank.advance)
    original_knots = vector_module.step_knots
    vector_module.step_knots = timed("knots (records of all envs, end of step)",
                                     original_knots)
    rng = np.random.default_rng(0)
    low, high = bare.single_action_space.low, bare.single_action_space.high
    actions = [rng.uniform(low, high, (n_envs, low.size)).astype(np.float32)
               for _ in range(steps)]
    bare_s = wrapped_s = 0.0
    try:
        for _ in range(repeats):
            bare.reset(seed=0)
            wrapped.reset(seed=0)
            for a in actions:
                t = time.process_time()
                bare.step(a)
                bare_s += time.process_time() - t
                t = time.process_time()
                wrapped.step(a)
                wrapped_s += time.process_time() - t
    finally:
        vector_module.step_knots = original_knots
    count = repeats * len(actions)
    print(f"breakdown legs_osl vector{n_envs} backend={backend} lag_physics_step={lag} "
          f"(ms per vector step, x: over the bare vector step)")
    rows = [("bare vector step", bare_s), ("wrapped vector step", wrapped_s),
            *spent.items()]
    for name, total in rows:
        print(f"  {name:55s} {total / count * 1e3:8.2f} ms {total / bare_s:7.3f} x")
    inner = spent["inner vector step (physics + recording)"]
    print(f"  {'inner vector step - bare vector step':55s} "
          f"{(inner - bare_s) / count * 1e3:8.2f} ms {(inner - bare_s) / bare_s:7.3f} x")
    bare.close()
    wrapped.close()


def counted_regions(steps: int, backend: str, lag: bool) -> None:
    """Runs under callgrind (:func:`instructions`): the bare legs env and the wrapped one step
    the same actions from the same reset, each pass of ``steps`` env steps a region that
    callgrind_control zeroes before and dumps after; an empty region first (the cost of
    marking a region), then the wrapper's end-of-step kinematics alone."""
    import os
    import subprocess

    def region(fn, n: int) -> None:
        pid = str(os.getpid())
        subprocess.run(["callgrind_control", "-z", pid], check=True, capture_output=True)
        time.sleep(0.2)  # callgrind polls its command file; a sleep costs no instructions
        for _ in range(n):
            fn()
        subprocess.run(["callgrind_control", "-d", pid], check=True, capture_output=True)
        time.sleep(0.2)

    path = myo_sim_model_path("legs_osl")
    compiled = mujoco.MjModel.from_xml_path(str(path))
    bare = MuscleModelEnv(path, frame_skip=FRAME_SKIP, model=compiled)
    wrapped = SpindleAfferents(MuscleModelEnv(path, frame_skip=FRAME_SKIP, model=compiled),
                               backend=backend, lag_physics_step=lag)
    rng = np.random.default_rng(0)
    low, high = bare.action_space.low, bare.action_space.high
    actions = [rng.uniform(low, high).astype(np.float32) for _ in range(steps + 5)]
    bare.reset(seed=0)
    wrapped.reset(seed=0)
    for a in actions[:5]:  # past the first steps' one-off work (buffers, caches)
        bare.step(a)
        wrapped.step(a)
    region(lambda: None, 1)
    for env in (bare, wrapped):
        todo = iter(actions[5:])
        region(lambda env=env, todo=todo: env.step(next(todo)), steps)
    region(lambda: wrapped.tap.state_now(), steps)


def instructions(steps: int, backend: str, lag: bool) -> None:
    """Instructions per env step (valgrind's callgrind: exact and the same on a loaded
    machine) of the bare legs env and of ``SpindleAfferents`` on it, and their ratio."""
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "cg.out"
        cmd = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", sys.executable,
               str(Path(__file__).resolve()), "--instructions-child", "--steps", str(steps),
               "--backends", backend, "--lag", str(int(lag))]
        env = {**os.environ, "PYTHONHASHSEED": "0"}
        subprocess.run(cmd, check=True, capture_output=True, env=env)
        counts = []
        for i in range(1, 5):
            text = (Path(tmp) / f"cg.out.{i}").read_text()
            counts.append(int(next(ln for ln in text.splitlines()
                                   if ln.startswith("summary:")).split()[1]))
    empty = counts[0]
    bare, wrapped, kinematics = ((c - empty) / steps for c in counts[1:])
    print(f"instructions per env step (callgrind, legs_osl single env, backend={backend}, "
          f"lag_physics_step={lag}, {steps} steps): bare {bare / 1e6:.3f} M, wrapped "
          f"{wrapped / 1e6:.3f} M, wrapper {(wrapped - bare) / 1e6:.3f} M (of it the "
          f"end-of-step kinematics {kinematics / 1e6:.3f} M); wrapped / bare "
          f"{wrapped / bare:.3f}")
    print(f"bench_wrapper_instructions bare={bare:.0f} wrapped={wrapped:.0f} "
          f"ratio={wrapped / bare:.3f}")


def myosuite_child(env_ids: list[str], steps: int, repeats: int) -> None:
    """Runs inside MyoSuite's interpreter: each env bare and wrapped (numpy and C), side by
    side; prints one line per env."""
    import myosuite  # noqa: F401  (registers the envs)

    from spindle.chain import resolve_backend

    backends = ("numpy", "c") if resolve_backend("auto") == "c" else ("numpy",)
    for env_id in env_ids:
        probe = SpindleAfferents(gym.make(env_id))
        source, n = probe.substep_source, probe.muscles.n
        rng = np.random.default_rng(0)
        space = probe.action_space
        actions = [rng.uniform(space.low, space.high).astype(np.float32) for _ in range(steps)]
        probe.close()
        makers = {b: (lambda b=b, e=env_id: SpindleAfferents(gym.make(e), backend=b))
                  for b in backends}
        b, wrapped, round_ratios = compare(lambda e=env_id: gym.make(e), makers, actions,
                                           repeats)
        cells = " ".join(f"{b_}: +{(w - b) * 1e3:.3f} ms = {(w - b) / (n * 1e-6):.2f} us/muscle "
                         f"= {round_ratios[b_]:.3f}x" for b_, w in wrapped.items())
        print(f"MYOSUITE {env_id} muscles={n} substep_source={source} bare={b * 1e3:.3f} ms "
              f"{cells}", flush=True)


def run_myosuite(python: str, env_ids: list[str], steps: int, repeats: int) -> list[str]:
    """:func:`myosuite_child` in MyoSuite's interpreter; its result lines."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": repo + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [python, str(Path(__file__).resolve()), "--myosuite-child", *env_ids,
           "--steps", str(steps), "--repeats", str(repeats)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("MYOSUITE ")]
    if out.returncode != 0:
        print(out.stderr[-2000:], file=sys.stderr)
        raise SystemExit(f"the MyoSuite run failed ({python}, exit {out.returncode})")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, nargs="+", default=[16, 64])
    parser.add_argument("--steps", type=int, default=40, help="env steps per measurement")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", nargs="+", default=None,
                        help="default: numpy and c (c if it builds here)")
    parser.add_argument("--lag", nargs="+", type=lambda x: {"0": False, "1": True}[x],
                        default=[False, True], metavar="{0,1}",
                        help="lag_physics_step settings to run (default: 0 1)")
    parser.add_argument("--models", nargs="+", default=["elbow", "legs_osl"],
                        choices=["elbow", "legs_osl"], help="myo-sim models (default: both)")
    parser.add_argument("--breakdown", type=int, metavar="N_ENVS",
                        help="only print where the time of a wrapped legs vector step of "
                             "N_ENVS envs goes (C backend if it builds, lagging; --backends, "
                             "--lag to change)")
    parser.add_argument("--figure", metavar="PNG",
                        help="only draw the docs figure (needs matplotlib) to this path")
    parser.add_argument("--myosuite-python", metavar="PATH",
                        help="also run MyoSuite envs in this interpreter (MyoSuite's venv)")
    parser.add_argument("--myosuite-envs", nargs="+",
                        default=["myoElbowPose1D6MRandom-v0", "myoElbowPoseTaskRandom-v0",
                                 "myoLegStandRandom-v0"])
    parser.add_argument("--myosuite-child", nargs="+", help=argparse.SUPPRESS)
    parser.add_argument("--instructions", action="store_true",
                        help="only count instructions per env step of the bare and the "
                             "wrapped legs env under valgrind (single env; C unless "
                             "--backends says otherwise; --lag's last setting)")
    parser.add_argument("--instructions-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.instructions or args.instructions_child:
        from spindle.chain import resolve_backend

        backend = (args.backends or [resolve_backend("auto")])[0]
        run = counted_regions if args.instructions_child else instructions
        run(args.steps, backend, args.lag[-1])
        return
    if args.myosuite_child:
        myosuite_child(args.myosuite_child, args.steps, args.repeats)
        return
    if args.figure:
        figure(args.figure)
        return
    from spindle.chain import resolve_backend

    if args.breakdown:
        backend = (args.backends or [resolve_backend("auto")])[0]
        breakdown(args.breakdown, backend, args.lag[-1], args.steps, args.repeats)
        return

    backends = tuple(args.backends or (("numpy", "c") if resolve_backend("auto") == "c"
                                       else ("numpy",)))
    ratios: dict[str, float] = {}
    head = " ".join(f"{'us/mus':>9s} {variant_name(b, lag) + ' x':>7s}"
                    for b in backends for lag in args.lag)
    print(f"{'model':9s} {'mode':9s} {'muscles':>7s} {'bare ms':>9s} {'mj_step ms':>10s} {head}")
    for name in args.models:
        bench_rows(name, args, backends, ratios)
    if "c" not in backends:
        print("C backend: not available here (no C compiler or cached build)")
    error = hermite_error_L0()
    print(f"Hermite fallback vs recorded physics steps, elbow, bang-bang: max |dL| = "
          f"{error:.4f} L0")
    if args.myosuite_python:
        for line in run_myosuite(args.myosuite_python, args.myosuite_envs, args.steps,
                                 args.repeats):
            print(line)
    keys = [k for k in ratios if k.startswith("legs_vector")] + \
        [k for k in ratios if not k.startswith("legs_vector")]
    print("bench_wrapper " + " ".join(f"{k}={ratios[k]:.3f}" for k in keys)
          + f" hermite_max_length_error_L0={error:.4f}")


if __name__ == "__main__":
    main()
