"""The Gymnasium envs: API conventions, timing against an independent replay of the physics,
physiology, reproducibility, bad input, vector envs, pickling and rendering."""

from __future__ import annotations

import math
import os
import pickle
import subprocess
import sys
import warnings
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import proprio_env
from proprio_env.body.model import JOINT, MUSCLES, SERVO, load_model
from proprio_env.body.muscle_length import fibre_state, muscle_geometry
from proprio_env.envs import RATE_SCALE_PPS, ElbowReachEnv, ProsthesisElbowEnv
from spindle.chain import BACKENDS, make_chain, run_chain
from spindle.chain.sensor import AX12, Calibration

ROOT = Path(__file__).resolve().parents[1]
IDS = ("proprio_env/ElbowReach-v0", "proprio_env/ProsthesisElbow-v0")


def rollout(env, actions, seed=0, options=None):
    obs, info = env.reset(seed=seed, options=options)
    out_obs, out_info = [obs], [info]
    for a in actions:
        obs, _, _, _, info = env.step(a)
        out_obs.append(obs)
        out_info.append(info)
    return np.array(out_obs), out_info


def random_actions(env, n, seed=1):
    env.action_space.seed(seed)
    return [env.action_space.sample() for _ in range(n)]


# -- registration and conventions ------------------------------------------------------------
def test_import_is_light_and_registers_both_ids():
    code = ("import sys, proprio_env, gymnasium; "
            "assert 'mujoco' not in sys.modules, 'mujoco imported'; "
            "assert 'proprio_env.envs' not in sys.modules, 'envs imported'; "
            "ids = [i for i in gymnasium.registry if i.startswith('proprio_env/')]; "
            "print(sorted(ids))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True).stdout
    # v1 (Ib observed) registered beside the v0 ids, which are unchanged
    assert out.strip() == str(sorted(IDS + tuple(i.replace("-v0", "-v1") for i in IDS)))


@pytest.mark.parametrize("env_id", IDS)
def test_make_spaces_and_truncation(env_id):
    env = gym.make(env_id)
    assert env.spec.max_episode_steps == proprio_env.MAX_EPISODE_STEPS == 200
    assert env.observation_space.shape == (5,)
    assert env.observation_space.dtype == np.float32
    env.reset(seed=3)
    steps, truncated = 0, False
    zero = np.clip(np.zeros(env.action_space.shape), env.action_space.low,
                   env.action_space.high).astype(np.float32)
    while not truncated:
        _, _, terminated, truncated, _ = env.step(zero)
        assert not terminated
        steps += 1
    assert steps == 200
    env.close()


@pytest.mark.parametrize("cls", [ElbowReachEnv, ProsthesisElbowEnv])
def test_gymnasium_check_env(cls):
    from gymnasium.utils.env_checker import check_env

    env = cls()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    # Our Box has infinite upper bounds on rates: that warning is expected, nothing else.
    unexpected = [str(w.message) for w in caught if "infinity" not in str(w.message).lower()
                  and "render" not in str(w.message).lower()]
    assert unexpected == []


@pytest.mark.parametrize("cls", [ElbowReachEnv, ProsthesisElbowEnv])
def test_stable_baselines3_check_env(cls):
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3.check_env(cls(), warn=False)


# -- the observation is the chain's output on the physics, replayed independently ------------
def replay_physics(env_cls, actions, seed):
    """Run a fresh MuJoCo model through the same actions, recording the angle and the exact
    fibre lengths (``fibre_state`` after ``mj_forward``) after every physics step."""
    env = env_cls()
    env.reset(seed=seed)
    angle0 = env.angle_deg
    model = load_model()
    model.opt.disableactuator = env.disabled_groups
    data = mujoco.MjData(model)
    qadr = model.jnt_qposadr[model.joint(JOINT).id]
    data.qpos[qadr] = math.radians(angle0)
    if env_cls is ProsthesisElbowEnv:
        data.ctrl[model.actuator(SERVO).id] = math.radians(angle0)
    mujoco.mj_forward(model, data)
    geoms = tuple(muscle_geometry(model, m) for m in MUSCLES)
    t, angle, length = [0.0], [angle0], [fibre_state(model, data, geoms)[0]]
    for a in actions:
        if env_cls is ElbowReachEnv:
            data.ctrl[[model.actuator(m).id for m in MUSCLES]] = a
        else:
            data.ctrl[model.actuator(SERVO).id] = math.radians(65 + 65 * float(a[0]))
        for _ in range(env.frame_skip):
            mujoco.mj_step(model, data)
            mujoco.mj_forward(model, data)
            t.append(data.time)
            angle.append(math.degrees(data.qpos[qadr]))
            length.append(fibre_state(model, data, geoms)[0])
    return np.array(t), np.array(angle), np.array(length), env.frame_skip


@pytest.mark.parametrize("source", ["exact", "reduced"])
def test_observation_is_chain_on_independent_replay(source):
    env = ElbowReachEnv(afferent_source=source)
    actions = random_actions(env, 25)
    obs, infos = rollout(env, actions, seed=5)
    t, angle, length, skip = replay_physics(ElbowReachEnv, actions, seed=5)
    np.testing.assert_allclose([i["angle_deg"] for i in infos], angle[::skip], atol=1e-9)
    if source == "exact":
        ref = run_chain(t, length_L0=length)
    else:
        ref = run_chain(t, angle_deg=angle)
    np.testing.assert_allclose(obs[:, 0:2] * RATE_SCALE_PPS, ref.ia_pps[::skip],
                               rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(obs[:, 2:4] * RATE_SCALE_PPS, ref.ii_pps[::skip],
                               rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose([i["ia_pps"] for i in infos], ref.ia_pps[::skip], rtol=1e-9,
                               atol=1e-9)
    np.testing.assert_allclose([i["gamma_static_pps"] for i in infos],
                               ref.gamma_static_pps[::skip], rtol=1e-9, atol=1e-9)


def test_encoder_source_matches_chain_on_ideal_readings():
    """With a noise-free, jitter-free encoder, the prosthesis env equals the chain run on the
    rounded counts of the replayed angle at every physics step."""
    ideal = AX12.ideal()
    env = ProsthesisElbowEnv(encoder_params=ideal)
    actions = random_actions(env, 20)
    _, infos = rollout(env, actions, seed=2)
    t, angle, _, skip = replay_physics(ProsthesisElbowEnv, actions, seed=2)
    counts = np.clip(np.rint(Calibration().counts(angle)), 0, ideal.max_count)
    # the chain starts at rest on the reset angle, then reads every physics step
    chain = make_chain(env.afferents.chain.config)
    chain.reset(angle[0], t[0])
    ia = [chain.last.ia_pps]
    for k in range(1, t.size):
        s = chain.push_counts(t[k], counts[k])
        if k % skip == 0:
            ia.append(s.ia_pps)
    np.testing.assert_allclose([i["ia_pps"] for i in infos], ia, rtol=1e-9, atol=1e-9)
    assert all(i["sensor_samples"] == skip for i in infos[1:])


@pytest.mark.parametrize("control_hz, samples", [(50, 10), (100, 5), (25, 20)])
@pytest.mark.parametrize("source", ["exact", "reduced", "encoder"])
def test_physics_sensor_and_spindles_end_each_step_together(control_hz, samples, source):
    env = ElbowReachEnv(control_hz=control_hz, afferent_source=source)
    assert env.dt == pytest.approx(1 / control_hz)
    _, infos = rollout(env, random_actions(env, 15))
    for k, info in enumerate(infos[1:], start=1):
        assert info["time_s"] == pytest.approx(k / control_hz, abs=1e-9)
        if source == "encoder":
            # ~500 Hz jittered readings: the last one lies within one period of the step end
            assert info["time_s"] - 0.0025 < info["sensor_time_s"] <= info["time_s"]
            assert abs(info["sensor_samples"] - samples) <= 1
        else:
            assert info["sensor_time_s"] == info["time_s"]
            assert info["sensor_samples"] == samples
    counters = env.afferents.chain.counters
    assert counters["repeated_time"] == counters["time_backwards"] == counters["gaps"] == 0


def test_control_rate_must_divide_physics():
    with pytest.raises(ValueError, match="control_hz"):
        ElbowReachEnv(control_hz=33.0)
    with pytest.raises(ValueError, match="control_hz"):
        ElbowReachEnv(control_hz=float("nan"))


# -- physiology and physics ----------------------------------------------------------------
def test_muscles_move_the_elbow_their_way():
    env = ElbowReachEnv()
    rollout(env, [np.array([1.0, 0.0], np.float32)] * 25, options={"angle_deg": 60})
    angle_flex = env.angle_deg
    rollout(env, [np.array([0.0, 1.0], np.float32)] * 25, options={"angle_deg": 60})
    angle_ext = env.angle_deg
    assert angle_flex > 100 and angle_ext < 20


def test_prosthesis_servo_reaches_command_and_spindles_feel_length():
    env = ProsthesisElbowEnv(afferent_source="reduced")
    ii = {}
    for command in (20.0, 110.0):
        a = np.array([(command - 65) / 65], np.float32)
        obs, infos = rollout(env, [a] * 100, options={"angle_deg": 65})
        # servo (kp 100 N m/rad) against gravity: a small steady-state lag only
        assert abs(infos[-1]["angle_deg"] - command) < 3.0
        assert infos[-1]["command_deg"] == pytest.approx(command, abs=1e-4)
        ii[command] = obs[-1, 2:4] * RATE_SCALE_PPS
    # Extension stretches the flexor (BRA), flexion the extensor (TRImed): II follows length.
    assert ii[20.0][0] > ii[110.0][0]
    assert ii[110.0][1] > ii[20.0][1]


def test_observation_layout_and_fusimotor_option():
    env = ElbowReachEnv(include_fusimotor=True)
    assert env.observation_space.shape == (9,)
    obs, info = env.reset(seed=0, options={"target_deg": 50.0})
    obs, *_, info = env.step(np.array([0.3, 0.2], np.float32))
    np.testing.assert_allclose(obs[:2], info["ia_pps"] / 100, rtol=1e-6)
    np.testing.assert_allclose(obs[2:4], info["ii_pps"] / 100, rtol=1e-6)
    assert obs[4] == pytest.approx(math.radians(50.0))
    np.testing.assert_allclose(obs[5:7], info["gamma_static_pps"] / 100, rtol=1e-6)
    np.testing.assert_allclose(obs[7:9], info["gamma_dynamic_pps"] / 100, rtol=1e-6)
    assert info["target_deg"] == 50.0
    assert info["angle_error_deg"] == pytest.approx(info["angle_deg"] - 50.0)
    # reward: -|error| in rad - 0.05 |a|^2
    _, reward, *_, info = env.step(np.array([0.3, 0.2], np.float32))
    expected = -abs(math.radians(info["angle_error_deg"])) - 0.05 * (0.09 + 0.04)
    assert reward == pytest.approx(expected, rel=1e-6)


def test_targets_come_from_the_given_ranges():
    env = ElbowReachEnv(target_ranges_deg=((20, 30), (80, 90)))
    targets = [env.reset(seed=s)[1]["target_deg"] for s in range(60)]
    assert all(20 <= x <= 30 or 80 <= x <= 90 for x in targets)
    assert any(x < 50 for x in targets) and any(x > 50 for x in targets)
    with pytest.raises(ValueError, match="target_ranges_deg"):
        ElbowReachEnv(target_ranges_deg=((20, 200),))


def test_glitching_encoder_never_puts_nan_in_observation():
    from dataclasses import replace

    env = ProsthesisElbowEnv(encoder_params=replace(AX12, invalid_rate=0.2))
    obs, _ = rollout(env, random_actions(env, 60))
    assert np.all(np.isfinite(obs))
    assert env.afferents.chain.counters["invalid_reading"] > 0


# -- reproducibility -------------------------------------------------------------------------
@pytest.mark.parametrize("env_id", IDS)
def test_seed_reproduces_episode_bit_for_bit(env_id):
    env_a, env_b = gym.make(env_id), gym.make(env_id)
    actions = random_actions(env_a, 40)
    obs_a, info_a = rollout(env_a, actions, seed=11)
    obs_b, info_b = rollout(env_b, actions, seed=11)
    assert obs_a.tobytes() == obs_b.tobytes()
    assert [i["angle_deg"] for i in info_a] == [i["angle_deg"] for i in info_b]
    obs_c, _ = rollout(env_b, actions, seed=12)
    assert obs_c.tobytes() != obs_a.tobytes()


def test_pickled_env_continues_identically():
    env = ProsthesisElbowEnv()
    actions = random_actions(env, 30)
    rollout(env, actions[:10], seed=4)
    clone = pickle.loads(pickle.dumps(env))
    for a in actions[10:]:
        o1, r1, *_ = env.step(a)
        o2, r2, *_ = clone.step(a)
        assert o1.tobytes() == o2.tobytes() and r1 == r2


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_vector_envs_match_single_envs(mode):
    env_id = "proprio_env/ElbowReach-v0"
    vec = gym.make_vec(env_id, num_envs=2, vectorization_mode=mode)
    try:
        obs, _ = vec.reset(seed=[7, 8])
        rng = np.random.default_rng(0)
        actions = rng.uniform(0, 1, (6, 2, 2)).astype(np.float32)
        vec_obs = [obs]
        for a in actions:
            obs, *_ = vec.step(a)
            vec_obs.append(obs)
    finally:
        vec.close()
    vec_obs = np.array(vec_obs)
    for i, seed in enumerate((7, 8)):
        single, _ = rollout(gym.make(env_id), list(actions[:, i]), seed=seed)
        assert single.tobytes() == vec_obs[:, i].tobytes()


# -- bad input -------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", [ElbowReachEnv, ProsthesisElbowEnv])
def test_bad_actions_raise_clear_errors(cls):
    env = cls()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(env.action_space.sample())
    env.reset(seed=0)
    n = env.action_space.shape[0]
    before = env.angle_deg, env.data.time
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.full(n, np.nan))
    with pytest.raises(ValueError, match="outside the action box"):
        env.step(np.full(n, 1.5))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(n + 1))
    assert (env.angle_deg, env.data.time) == before  # nothing advanced


def test_clip_actions_clips_instead():
    clipped, plain = ElbowReachEnv(clip_actions=True), ElbowReachEnv()
    o1, _ = rollout(clipped, [np.array([2.0, -1.0])] * 5, seed=1)
    o2, _ = rollout(plain, [np.array([1.0, 0.0])] * 5, seed=1)
    assert o1.tobytes() == o2.tobytes()
    with pytest.raises(ValueError, match="NaN"):
        clipped.step(np.array([np.nan, 0.0]))


def test_bad_arguments_and_options():
    with pytest.raises(ValueError, match="backend"):
        ElbowReachEnv(backend="fortran")
    assert "numpy" in BACKENDS
    with pytest.raises(ValueError, match="afferent_source"):
        ElbowReachEnv(afferent_source="telepathy")
    env = ElbowReachEnv()
    with pytest.raises(ValueError, match="target_deg"):
        env.reset(options={"target_deg": 500})
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"speed": 1})


# -- rendering (headless: MUJOCO_GL=egl unless set otherwise) ---------------------------------
def test_rgb_array_render_shows_the_arm():
    code = """
import numpy as np
from proprio_env.envs import ElbowReachEnv
env = ElbowReachEnv(render_mode="rgb_array", width=160, height=160)
imgs = []
for angle in (10.0, 120.0):
    env.reset(seed=0, options={"angle_deg": angle})
    imgs.append(env.render())
env.close()
a, b = (i.astype(float) for i in imgs)
assert imgs[0].shape == (160, 160, 3) and imgs[0].dtype == np.uint8, imgs[0].shape
background = np.median(a.reshape(-1, 3), axis=0)
arm = np.abs(a - background).sum(axis=-1) > 60
changed = np.abs(a - b).sum(axis=-1) > 60
print(arm.mean(), changed.mean())
"""
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    arm_fraction, changed_fraction = map(float, out.stdout.split())
    # the arm covers part of the picture (not blank, not all arm) and moves with the angle
    assert 0.01 < arm_fraction < 0.5
    assert changed_fraction > 0.005


def test_render_without_a_gl_backend_says_how_to_get_one():
    """GLFW without a display cannot make a context: the error names the backend tried and the
    fix, in place of GLFW's warnings and MuJoCo's FatalError."""
    code = """
from proprio_env.envs import ElbowReachEnv
env = ElbowReachEnv(render_mode="rgb_array", width=32, height=32)
env.reset(seed=0)
try:
    env.render()
except RuntimeError as exc:
    print(exc)
else:
    raise SystemExit("rendered without a display")
"""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MUJOCO_GL"] = "glfw"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    message = out.stdout
    assert "MUJOCO_GL=glfw" in message and "MUJOCO_GL=egl" in message
    assert "libegl1 libegl-mesa0 libgl1-mesa-dri" in message and "osmesa" in message
    assert "GLFWError" not in out.stderr  # GLFW's own warnings are folded into the message
