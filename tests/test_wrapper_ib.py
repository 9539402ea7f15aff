"""Ib (tendon organs) in the any-model wrappers: the forces against an independent shadow of
the physics (mj_step then mj_forward at every physics step), Ib against
``spindle.tendon_organ.simulate`` on those forces (the other backend) and the reference
solver; the option, copies, the vector wrapper and the trajectory function."""

from __future__ import annotations

import copy
import pickle

import gymnasium as gym
import mujoco
import numpy as np
import pytest

from proprio_env.body.model import model_path
from proprio_env.wrappers import SpindleAfferents, SpindleAfferentsVector, afferents_from_trajectory
from spindle.tendon_organ import simulate
from spindle.tendon_organ_params import HUMAN, force_scales_N
from spindle.tendon_organ_reference import reference_rates

pytest.importorskip("imageio", reason="gymnasium.envs.mujoco needs imageio")
from proprio_env.wrappers.mjcf_env import MuscleModelEnv, myo_sim_model_path

IB = ("ia", "ii", "ib")


def elbow_env() -> MuscleModelEnv:
    env = MuscleModelEnv(model_path(), frame_skip=10)
    env.model.opt.disableactuator = 1 << 2  # the servo off: the muscles move the elbow
    return env


def myo_elbow_env() -> MuscleModelEnv:
    pytest.importorskip("myo_sim", reason="myo-sim is not installed (the 'myo' extra)")
    return MuscleModelEnv(myo_sim_model_path("elbow"), frame_skip=10)


def shadow_forces(env, actions):
    """Tendon tension (N) of every muscle after every physics step of an independent shadow:
    the env's reset state copied, stepped one mj_step at a time with mj_forward after each
    (MuJoCo's full forward, not the wrapper's scratch stages)."""
    base = env.unwrapped
    model, data = base.model, base.data
    shadow = mujoco.MjData(model)
    shadow.qpos[:], shadow.qvel[:], shadow.act[:] = data.qpos, data.qvel, data.act
    shadow.time = data.time
    mujoco.mj_forward(model, shadow)
    ids = env.muscles.ids
    out = [-shadow.actuator_force[ids].copy()]
    for a in actions:
        shadow.ctrl[:] = a
        for _ in range(base.frame_skip):
            mujoco.mj_step(model, shadow)
            mujoco.mj_forward(model, shadow)
            out.append(-shadow.actuator_force[ids].copy())
    return np.array(out)


def run(env, actions, seed):
    _, info = env.reset(seed=seed)
    f0 = shadow_forces(env, actions)  # from the reset state, before stepping
    infos = [info]
    for a in actions:
        infos.append(env.step(a)[4])
    return f0, infos


@pytest.mark.parametrize("make", [elbow_env, myo_elbow_env], ids=["elbow", "myo_elbow"])
def test_ib_is_the_organs_on_independently_recorded_forces(make):
    env = SpindleAfferents(make(), afferents=IB, backend="c")
    assert env.substep_source == "frames"
    n_muscles = env.muscles.n
    rng = np.random.default_rng(0)
    space = env.action_space
    actions = rng.uniform(space.low, space.high, (12, *space.shape))
    forces, infos = run(env, actions, seed=1)
    skip = env.unwrapped.frame_skip
    np.testing.assert_allclose(np.array([i["tendon_force_N"] for i in infos]),
                               forces[::skip], rtol=1e-12, atol=1e-9)  # measured: equal (0.0)
    assert forces.max() > 20.0
    scales = force_scales_N(HUMAN, env.unwrapped.model.actuator_gainprm[env.muscles.ids, 2])
    dt = float(env.unwrapped.model.opt.timestep)
    want = simulate(forces, dt, scales, HUMAN, backend="numpy")
    ib = np.array([i["tendon_ib_pps"] for i in infos])
    assert np.abs(ib - want[::skip]).max() <= 1e-9  # C organs against numpy: 2.8e-14
    obs = env.step(actions[0])[0]
    np.testing.assert_allclose(obs[-n_muscles:] * 100.0, env.forces.ib_pps[0], rtol=1e-6)
    # and against the continuous system solved with scipy (the first muscle)
    t = np.arange(forces.shape[0]) * dt
    ref = reference_rates(lambda s: np.interp(s, t, forces[:, 0]), t, scales[0], HUMAN)
    # measured 2.0e-5 pps (elbow), 1.4e-3 pps (myo-sim's elbow)
    assert np.abs(ib[:, 0] - ref[::skip]).max() <= 5e-3
    assert ib.max() > 5.0 and np.all(ib >= 0)


def test_default_afferents_are_unchanged_and_info_has_the_forces():
    plain, with_ib = SpindleAfferents(elbow_env()), SpindleAfferents(elbow_env(), afferents=IB)
    base_dim = plain.env.observation_space.shape[0]
    assert plain.observation_space.shape == (base_dim + 4,)
    assert with_ib.observation_space.shape == (base_dim + 6,)
    o1, i1 = plain.reset(seed=0)
    o2, i2 = with_ib.reset(seed=0)
    a = np.array([0.8, 0.1, 0.0], np.float32)
    for _ in range(5):
        o1, *_, i1 = plain.step(a)
        o2, *_, i2 = with_ib.step(a)
    np.testing.assert_array_equal(o1, o2[:-2])
    np.testing.assert_array_equal(i1["tendon_force_N"], i2["tendon_force_N"])
    assert "tendon_ib_pps" not in i1 and i2["tendon_force_N"][0] > 100.0
    only_ib = SpindleAfferents(elbow_env(), afferents=("ib",), observation="dict")
    assert set(only_ib.observation_space.spaces) == {"observation", "tendon_ib"}
    for bad in ((), ("ia", "ia"), ("ib", "gto"), 3):
        with pytest.raises(ValueError, match="afferents="):
            SpindleAfferents(elbow_env(), afferents=bad)


def test_hermite_path_takes_the_line_between_the_ends_forces():
    env = SpindleAfferents(elbow_env(), afferents=IB, substep_source="hermite",
                           backend="numpy")
    _, info = env.reset(seed=2)
    ends = [info["tendon_force_N"]]
    for i in range(8):
        ends.append(env.step(np.array([0.9 * (i % 2), 0.5, 0.0], np.float32))[4][
            "tendon_force_N"])
        ib = env.forces.ib_pps[0]
    ends = np.array(ends)
    s = np.arange(0, 81) / 10
    line = np.stack([np.interp(s, np.arange(9), ends[:, j]) for j in range(2)], axis=1)
    scales = force_scales_N(HUMAN, env.unwrapped.model.actuator_gainprm[env.muscles.ids, 2])
    want = simulate(line, 2e-3, scales, HUMAN, backend="c")
    assert np.abs(ib - want[-1]).max() <= 1e-9


@pytest.mark.parametrize("backend", ["numpy", "c"])
def test_vector_sub_env_equals_single_wrapper_and_copies_continue(backend):
    single = SpindleAfferents(elbow_env(), afferents=IB, backend=backend)
    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv([elbow_env, elbow_env]),
                                 afferents=IB, backend=backend)
    o, _ = vec.reset(seed=[5, 6])
    s, _ = single.reset(seed=6)
    a = np.array([[0.2, 0.9, 0.0], [0.9, 0.2, 0.0]], np.float32)
    for _ in range(4):
        o, *_, info = vec.step(a)
        s, *_, si = single.step(a[1])
    np.testing.assert_allclose(o[1], s, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(info["tendon_ib_pps"][1], si["tendon_ib_pps"], atol=1e-12)
    copies = [copy.deepcopy(single), pickle.loads(pickle.dumps(single))]
    for _ in range(3):
        want = single.step(a[0])[0]
        for c in copies:
            np.testing.assert_array_equal(c.step(a[0])[0], want)


def test_trajectory_gives_ib_only_with_forces():
    model = mujoco.MjModel.from_xml_path(str(model_path()))
    t = np.arange(101) * 0.01
    qpos = (0.5 + 0.4 * np.sin(2 * np.pi * t))[:, None]
    plain = afferents_from_trajectory(model, qpos, t)
    assert plain.ib_pps is None and plain.force_N is None
    force = np.stack([300 + 200 * np.sin(3 * t), 50 + 40 * np.cos(5 * t)], axis=1)
    out = afferents_from_trajectory(model, qpos, t, force_N_t=force, backend="c")
    scales = force_scales_N(HUMAN, [987.26, 624.3])
    np.testing.assert_allclose(out.ib_pps, simulate(force, 0.01, scales, HUMAN, "numpy"),
                               atol=1e-9)
    np.testing.assert_array_equal(out.ia_pps, plain.ia_pps)
    with pytest.raises(ValueError, match="force_N_t"):
        afferents_from_trajectory(model, qpos, t, force_N_t=force[:, :1])
    bad = force.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="force_N_t"):
        afferents_from_trajectory(model, qpos, t, force_N_t=bad)
