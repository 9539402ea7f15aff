"""The spindle-afferent wrappers on this project's elbow (no optional packages needed)."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import proprio_env  # noqa: F401  (registers the envs)
from proprio_env.body.model import JOINT, MUSCLES, load_model, model_path
from proprio_env.body.muscle_length import sweep
from proprio_env.wrappers import (
    ConstantFusimotor,
    SpindleAfferents,
    SpindleAfferentsVector,
    TemplateFusimotor,
    afferents_from_trajectory,
    find_muscles,
)
from proprio_env.wrappers.bank import SpindleDriver
from proprio_env.wrappers.muscles import ActuatorKinematics
from spindle import core
from spindle.chain import ArmChain, ChainConfig
from spindle.params import HUMAN

pytest.importorskip("imageio", reason="gymnasium.envs.mujoco needs imageio")
from proprio_env.wrappers.mjcf_env import MuscleModelEnv

SERVO_OFF = 1 << 2  # actuator group 2: the elbow's position servo

PENNATION_GAP_L0 = 0.0216
"""The largest fibre-length difference between the OpenSim-derived exact model and MuJoCo's
normalisation on the elbow (TRImed at 0 deg, 0.02153 L0; docs/wrapper.md)."""


def elbow_env(**kwargs) -> MuscleModelEnv:
    env = MuscleModelEnv(model_path(), frame_skip=10)
    env.model.opt.disableactuator = SERVO_OFF
    return env


def bang_bang(i: int, period: int = 10) -> np.ndarray:
    a = np.zeros(3, dtype=np.float32)
    a[:2] = (1.0, 0.0) if (i // period) % 2 == 0 else (0.0, 1.0)
    return a


def test_mujoco_normalisation_is_the_exact_length_less_pennation():
    model = load_model()
    muscles = find_muscles(model)
    assert muscles.names == MUSCLES
    lo, hi = model.joint(JOINT).range
    s = sweep(model, np.linspace(lo, hi, 1301))
    mujoco_L = muscles.length_L0(s.mtu_length_m)
    gap = s.fibre_length_L0 - mujoco_L
    # BRA has no pennation: the two models are the same; TRImed's fibres are longer than
    # their projection on the tendon by at most the documented figure
    assert np.abs(gap[:, 0]).max() < 1e-12
    assert gap[:, 1].min() >= 0
    assert 0.02 < gap[:, 1].max() <= PENNATION_GAP_L0


def test_scratch_kinematics_equal_mj_forward_and_leave_the_env_data_alone():
    model = load_model()
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    kin = ActuatorKinematics(model, find_muscles(model).ids)
    for _ in range(20):
        data.qpos[:] = rng.uniform(0.0, 2.2, model.nq)
        data.qvel[:] = rng.normal(0.0, 5.0, model.nv)
        mujoco.mj_forward(model, data)
        before = data.xpos.copy()
        length, velocity = kin.of_data(data)
        np.testing.assert_array_equal(length, data.actuator_length[:2])
        np.testing.assert_allclose(velocity, data.actuator_velocity[:2], rtol=0, atol=1e-15)
        np.testing.assert_array_equal(before, data.xpos)


def test_recording_the_physics_steps_changes_nothing_in_the_env():
    bare, wrapped = elbow_env(), SpindleAfferents(elbow_env())
    assert wrapped.substep_source == "frames"
    o1, _ = bare.reset(seed=4)
    o2, _ = wrapped.reset(seed=4)
    n = o1.size
    np.testing.assert_array_equal(o1, o2[:n])
    for i in range(30):
        o1, *_ = bare.step(bang_bang(i))
        o2, *_ = wrapped.step(bang_bang(i))
        np.testing.assert_array_equal(o1, o2[:n])
    assert wrapped.observation_space.contains(o2)


def test_recorded_physics_steps_are_the_states_at_each_step_start_bit_for_bit():
    """The recorder's times, lengths and velocities are data.time, actuator_length and
    actuator_velocity as mj_step leaves them, step by step (a shadow stepped one call at a
    time and read back after each), over many steps (the times are accumulated, not read)."""
    from proprio_env.wrappers.capture import FrameRecorder

    env = elbow_env()
    env.reset(seed=3)
    model, data = env.model, env.data
    recorder = FrameRecorder(env, np.arange(model.nu))
    shadow = mujoco.MjData(model)
    for i in range(60):
        ctrl = bang_bang(i, 7)
        shadow.qpos[:], shadow.qvel[:], shadow.act[:] = data.qpos, data.qvel, data.act
        shadow.time, shadow.ctrl[:] = data.time, ctrl
        want = []
        for _ in range(10):
            t = shadow.time
            mujoco.mj_step(model, shadow)
            want.append((t, shadow.actuator_length.copy(), shadow.actuator_velocity.copy()))
        env.step(ctrl)
        times, lengths, velocities = recorder.take()
        np.testing.assert_array_equal(times, [w[0] for w in want])
        np.testing.assert_array_equal(lengths, [w[1] for w in want])
        np.testing.assert_array_equal(velocities, [w[2] for w in want])
    assert data.time == shadow.time


def test_wrapper_equals_the_chain_fed_the_same_lengths():
    """The wrapper (physics steps recorded) against ``ArmChain`` fed the same normalised
    lengths at every physics step, unfiltered, with the same fusimotor model: the chain
    takes its Hermite slopes from finite differences, the wrapper from MuJoCo's velocities;
    nothing else differs."""
    env = SpindleAfferents(elbow_env(), fusimotor=TemplateFusimotor(
        length_min_L0=(0.75, 0.75), length_max_L0=(1.05, 1.05)))
    model = env.unwrapped.model
    muscles, kin = env.muscles, ActuatorKinematics(model, env.muscles.ids)
    chain = ArmChain(ChainConfig(lowpass_hz=None))
    chain.length_min_L0[:], chain.length_max_L0[:] = 0.75, 1.05
    chain._arms._fusimotor.length_min_L0[:] = 0.75  # h(x)'s span as the wrapper's
    chain._arms._fusimotor.length_max_L0[:] = 1.05
    _, info = env.reset(seed=1)
    data = env.unwrapped.data
    chain.reset(0.0, data.time, length_L0=info["spindle_length_L0"])
    worst_ia, worst_ii = np.zeros(2), np.zeros(2)
    for i in range(60):
        ctrl = bang_bang(i, period=7)
        # the same physics on a copy, to read every physics step's lengths
        shadow = mujoco.MjData(model)
        shadow.qpos[:], shadow.qvel[:], shadow.act[:] = data.qpos, data.qvel, data.act
        shadow.time = data.time
        shadow.ctrl[:] = ctrl
        t, L = [], []
        for _ in range(10):
            mujoco.mj_step(model, shadow)
            t.append(shadow.time)
            L.append(muscles.length_L0(kin.of_data(shadow)[0]))
        sample = chain.push_lengths_block(np.array(t), np.array(L))
        _, _, _, _, info = env.step(ctrl)
        np.testing.assert_array_equal(info["spindle_measured_length_L0"], L[-1])
        worst_ia = np.maximum(worst_ia, np.abs(info["spindle_ia_pps"] - sample.ia_pps))
        worst_ii = np.maximum(worst_ii, np.abs(info["spindle_ii_pps"] - sample.ii_pps))
        np.testing.assert_array_equal(info["spindle_gamma_dynamic_pps"],
                                      sample.gamma_dynamic_pps)
    # measured (2026-12-02) Ia 0.0037 / 0.0033 pps, II 0.0012 / 0.0023 pps (BRA / TRImed):
    # the Hermite slopes' difference only
    assert worst_ia.max() < 0.005, worst_ia
    assert worst_ii.max() < 0.003, worst_ii


def test_wrapper_on_elbow_reach_agrees_with_the_exact_length_chain():
    """On ``ElbowReach-v0`` (lengths only at env-step ends: Hermite) against the env's own
    chain on exact lengths with the same fusimotor: BRA (no pennation) within the Hermite
    difference, TRImed's lengths within the documented normalisation gap."""
    config = ChainConfig(lowpass_hz=None)
    env = gym.make("proprio_env/ElbowReach-v0", afferent_source="exact", chain_config=config)
    chain = env.unwrapped.afferents.chain
    w = SpindleAfferents(env, fusimotor=TemplateFusimotor(
        length_min_L0=tuple(chain.length_min_L0), length_max_L0=tuple(chain.length_max_L0)))
    assert w.substep_source == "hermite"
    w.reset(seed=3)
    rng = np.random.default_rng(3)
    d_ia, d_len = [], []
    for i in range(100):
        if i % 5 == 0:
            action = rng.uniform(0.0, 1.0, 2).astype(np.float32)
        obs, _, _, _, info = w.step(action)
        assert np.all(np.isfinite(obs))
        d_ia.append(info["spindle_ia_pps"] - info["ia_pps"])
        d_len.append(info["spindle_length_L0"] - info["length_L0"])
        np.testing.assert_array_equal(info["spindle_gamma_dynamic_pps"][0],
                                      info["gamma_dynamic_pps"][0])
    d_ia, d_len = np.abs(d_ia), np.array(d_len)
    assert np.abs(d_len[:, 0]).max() < 1e-12
    assert 0 < -d_len[:, 1].min() <= PENNATION_GAP_L0 and d_len[:, 1].max() <= 0
    # BRA: only the sub-step curve differs (Hermite over 20 ms against the chain's 2 ms)
    assert d_ia[:, 0].max() < 4.0 and d_ia[:, 0].mean() < 0.5


@pytest.mark.parametrize("lag", [False, True])
def test_vector_sub_env_equals_the_single_wrapper(lag):
    n, seed = 3, 11
    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv([elbow_env] * n),
                                 lag_physics_step=lag)
    singles = [SpindleAfferents(elbow_env(), lag_physics_step=lag) for _ in range(n)]
    obs_v, _ = vec.reset(seed=seed)
    for i, s in enumerate(singles):
        obs_s, _ = s.reset(seed=seed + i)
        np.testing.assert_allclose(obs_v[i], obs_s, rtol=0, atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(25):
        actions = rng.uniform(0, 1, (n, 3)).astype(np.float32)
        obs_v, _, _, _, info_v = vec.step(actions)
        for i, s in enumerate(singles):
            obs_s, _, _, _, info_s = s.step(actions[i])
            # one batched state against floats on a few spindles: rounding only
            np.testing.assert_allclose(info_v["spindle_ia_pps"][i], info_s["spindle_ia_pps"],
                                       rtol=0, atol=1e-9)
            np.testing.assert_allclose(obs_v[i], obs_s, rtol=0, atol=1e-9)


@pytest.mark.parametrize("lag", [False, True])
def test_vector_autoreset_re_equilibrates_the_ended_env(lag):
    def make():
        return gym.wrappers.TimeLimit(elbow_env(), max_episode_steps=5)

    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv([make, make]), lag_physics_step=lag)
    vec.reset(seed=0)
    for step in range(12):
        actions = np.tile(bang_bang(step, 2), (2, 1))
        obs, _, _, trunc, info = vec.step(actions)
        assert trunc.all() == (step in (4, 10))  # 5 steps, then the reset step
        if step == 5:  # the step after the time limit: both envs reset (NEXT_STEP)
            assert vec.env.envs[0].unwrapped.data.time == 0.0
            rest = core.equilibrium_state(info["spindle_length_L0"][0], 100.0, 85.0, HUMAN)
            ia, ii = core.afferents(rest, HUMAN)
            np.testing.assert_allclose(info["spindle_ia_pps"][0], ia, atol=1e-9)
            np.testing.assert_allclose(info["spindle_ii_pps"][0], ii, atol=1e-9)
            assert not np.any(info["spindle_length_clamped"])
        assert np.all(np.isfinite(obs))


def test_afferents_from_trajectory_equal_the_wrapper_along_the_same_motion():
    env = SpindleAfferents(elbow_env())
    model = env.unwrapped.model
    env.reset(seed=2)
    data = env.unwrapped.data
    qpos, qvel, t = [data.qpos.copy()], [data.qvel.copy()], [data.time]
    ia, ii = [], []
    for i in range(40):
        ctrl = bang_bang(i, 4)
        shadow = mujoco.MjData(model)
        shadow.qpos[:], shadow.qvel[:], shadow.act[:] = data.qpos, data.qvel, data.act
        shadow.time, shadow.ctrl[:] = data.time, ctrl
        for _ in range(10):
            mujoco.mj_step(model, shadow)
            qpos.append(shadow.qpos.copy())
            qvel.append(shadow.qvel.copy())
            t.append(shadow.time)
        _, _, _, _, info = env.step(ctrl)
        ia.append(info["spindle_ia_pps"])
        ii.append(info["spindle_ii_pps"])
    t = np.array(t)
    t = t[0] + np.arange(t.size) * model.opt.timestep  # uniform (the sums of mj_step's dt)
    out = afferents_from_trajectory(model, np.array(qpos), t, qvel_t=np.array(qvel))
    np.testing.assert_allclose(out.ia_pps[10::10], ia, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.ii_pps[10::10], ii, rtol=0, atol=1e-9)
    # without velocities: second-order differences of the lengths, close to the same
    approx = afferents_from_trajectory(model, np.array(qpos), t)
    assert np.abs(approx.ia_pps - out.ia_pps).max() < 2.0


def shadow_physics_steps(model, data, ctrl, n_steps):
    """(qpos, qvel) after each of the next ``n_steps`` physics steps from ``data``'s state
    with ``ctrl``, on a copy (the env's own steps are the same, bit for bit)."""
    shadow = mujoco.MjData(model)
    shadow.qpos[:], shadow.qvel[:], shadow.act[:] = data.qpos, data.qvel, data.act
    shadow.time, shadow.ctrl[:] = data.time, ctrl
    out = []
    for _ in range(n_steps):
        mujoco.mj_step(model, shadow)
        out.append((shadow.qpos.copy(), shadow.qvel.copy()))
    return out


def test_lagging_one_physics_step_gives_the_afferents_one_physics_step_earlier():
    """lag_physics_step=True: after env step k the rates are those of the motion up to the
    state after physics step 10k - 1, exactly (afferents_from_trajectory on the same states,
    the spindles at rest from one physics step before the reset); the default's are those up
    to physics step 10k."""
    lagged, current = (SpindleAfferents(elbow_env(), lag_physics_step=lag) for lag in (True, False))
    model = lagged.unwrapped.model
    for env in (lagged, current):
        env.reset(seed=2)
    data = lagged.unwrapped.data
    states = [(data.qpos.copy(), data.qvel.copy())] * 2  # at rest one physics step before
    ia_lagged, ia_current = [], []
    for i in range(30):
        ctrl = bang_bang(i, 4)
        states += shadow_physics_steps(model, data, ctrl, 10)
        ia_lagged.append(lagged.step(ctrl)[4]["spindle_ia_pps"])
        ia_current.append(current.step(ctrl)[4]["spindle_ia_pps"])
    qpos, qvel = (np.array([s[j] for s in states]) for j in (0, 1))
    t = data.time - (len(states) - 2) * model.opt.timestep \
        + np.arange(-1, len(states) - 1) * model.opt.timestep
    out = afferents_from_trajectory(model, qpos, t, qvel_t=qvel)
    np.testing.assert_allclose(out.ia_pps[10::10], ia_lagged, rtol=0, atol=1e-9)
    # sample 10k + 1 is the state after physics step 10k: the default wrapper's
    np.testing.assert_allclose(out.ia_pps[11::10], ia_current, rtol=0, atol=1e-9)
    assert np.abs(np.array(ia_lagged) - np.array(ia_current)).max() > 1.0


def test_out_of_range_lengths_are_clamped_and_counted_never_nan():
    bank = SpindleDriver(2, np.full(3, 0.7), np.full(3, 1.3))
    bank.reset(None, np.zeros(2), np.array([[0.3, 1.0, 1.7], [1.0, 1.0, np.nan]]))
    np.testing.assert_array_equal(bank.counters["length_clamped"], [[1, 0, 1], [0, 0, 1]])
    np.testing.assert_array_equal(bank.length_L0, [[0.5, 1.0, 1.5], [1.0, 1.0, 0.5]])
    t = np.array([[0.002, 0.002], [0.004, 0.004]])
    L = np.array([[[0.2, 1.1, 2.0], [1.0, 1.9, 1.0]], [[0.2, 1.1, 2.0], [1.0, 1.9, 1.0]]])
    ia, ii = bank.advance(t, L, np.zeros_like(L))
    assert np.all(np.isfinite(ia)) and np.all(np.isfinite(ii))
    assert bank.length_L0.min() >= 0.5 and bank.length_L0.max() <= 1.5
    # 1.0 -> 1.1 in 2 ms is 50 L0/s: slew-limited to 8 L0/s (0.016 L0 per knot)
    np.testing.assert_allclose(bank.length_L0[0, 1], 1.0 + 2 * 0.016)
    assert bank.counters["slew_limited"][0, 1] == 2


def test_bad_arguments_name_the_value():
    with pytest.raises(ValueError, match="not an actuator"):
        SpindleAfferents(elbow_env(), muscles=["BRA", "nope"])
    with pytest.raises(ValueError, match="no muscle gain"):
        SpindleAfferents(elbow_env(), muscles=["r_elbow_servo"])
    with pytest.raises(ValueError, match="substep_source"):
        SpindleAfferents(elbow_env(), substep_source="sometimes")
    with pytest.raises(ValueError, match="lag_physics_step=True needs the recorded"):
        SpindleAfferents(elbow_env(), substep_source="hermite", lag_physics_step=True)
    with pytest.raises(ValueError, match="gamma_static_pps"):
        ConstantFusimotor(gamma_static_pps=-1.0)
    with pytest.raises(ValueError, match="uniform"):
        afferents_from_trajectory(load_model(), np.zeros((3, 1)), np.array([0, 0.1, 0.3]))
    async_env = gym.vector.AsyncVectorEnv([elbow_env] * 2)
    try:
        with pytest.raises(ValueError, match="SyncVectorEnv"):
            SpindleAfferentsVector(async_env)
    finally:
        async_env.close()


def test_dict_observation_keeps_the_env_observation():
    env = SpindleAfferents(elbow_env(), observation="dict", rate_scale_pps=1.0)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    np.testing.assert_array_equal(obs["spindle_ia"], info["spindle_ia_pps"])
    obs, *_ = env.step(bang_bang(0))
    assert env.observation_space.contains(obs)


def c_backend_available() -> bool:
    from spindle.chain import resolve_backend

    return resolve_backend("auto") == "c"


@pytest.mark.skipif(not c_backend_available(), reason="no C compiler or cached C build")
@pytest.mark.parametrize("fusimotor", [None, TemplateFusimotor()])
def test_c_backend_equals_numpy_backend(fusimotor):
    """The same wrapper on the C batch step and on the numpy core: the same rates to 1e-9 pps
    (the C step multiplies by reciprocals where numpy divides), with a reset in between."""
    n = 3

    def make():
        return gym.wrappers.TimeLimit(elbow_env(), max_episode_steps=12)

    vecs = {b: SpindleAfferentsVector(gym.vector.SyncVectorEnv([make] * n), backend=b,
                                      fusimotor=fusimotor) for b in ("numpy", "c")}
    assert vecs["c"].bank.backend == "c"
    for v in vecs.values():
        v.reset(seed=4)
    rng = np.random.default_rng(1)
    worst, top = 0.0, 0.0
    for i in range(30):
        actions = np.where(rng.random((n, 3)) < 0.5, bang_bang(i, 3), 0.3).astype(np.float32)
        infos = {b: v.step(actions)[4] for b, v in vecs.items()}
        for key in ("spindle_ia_pps", "spindle_ii_pps"):
            worst = max(worst, np.abs(infos["c"][key] - infos["numpy"][key]).max())
        top = max(top, infos["c"]["spindle_ia_pps"].max())
    assert top > 30
    assert worst <= 1e-9
    # the offline replay too, with its per-knot record
    model = vecs["c"].env.envs[0].unwrapped.model
    t = np.arange(200) * 2e-3
    qpos = (1.2 + 0.8 * np.sin(2 * np.pi * 1.5 * t))[:, None]
    out = {b: afferents_from_trajectory(model, qpos, t, backend=b) for b in ("numpy", "c")}
    np.testing.assert_allclose(out["c"].ia_pps, out["numpy"].ia_pps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(out["c"].ii_pps, out["numpy"].ii_pps, rtol=0, atol=1e-9)


def test_backend_names_are_checked():
    with pytest.raises(ValueError, match="backend='fortran'"):
        SpindleAfferents(elbow_env(), backend="fortran")
