"""The v1 envs: Ib (Golgi tendon organs) of BRA and TRImed in the observation, from the
tendon forces MuJoCo computes, against an independent replay of the physics and the
tendon-organ reference solver; v0 unchanged; vector sub-envs equal to single envs."""

from __future__ import annotations

import copy
import math
import pickle

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from test_env import rollout
from test_vector_env import compare_with_singles

import proprio_env  # noqa: F401  (registers the envs)
from proprio_env.body.force_sense import TendonForceSense
from proprio_env.body.model import JOINT, MUSCLES, SERVO, load_model
from proprio_env.body.moment_arm_fitting import moment_arms_exact_m
from proprio_env.envs import RATE_SCALE_PPS, ElbowReachEnv, ProsthesisElbowEnv
from spindle.tendon_organ import MAX_FORCE_N
from spindle.tendon_organ_params import ARM26_MAX_ISOMETRIC_FORCE_N, HUMAN, force_scales_N
from spindle.tendon_organ_reference import reference_rates

V1 = ("proprio_env/ElbowReach-v1", "proprio_env/ProsthesisElbow-v1")
G2 = force_scales_N(HUMAN, [ARM26_MAX_ISOMETRIC_FORCE_N[m] for m in MUSCLES])


def actions_for(env, steps, seed=3):
    rng = np.random.default_rng(seed)
    space = env.action_space
    return rng.uniform(space.low, space.high, (steps, *space.shape)).astype(np.float32)


def replay_forces(env, actions, angle0_deg):
    """A fresh MuJoCo model through the same actions from the env's reset state, with
    ``mj_forward`` after every ``mj_step``: (times, tendon forces (T, 2) N) after every
    physics step. The muscles' tension is -actuator_force; the prosthesis's servo torque is
    split with MuJoCo's exact moment arms (not the env's table)."""
    model = load_model()
    model.opt.disableactuator = env.unwrapped.disabled_groups
    data = mujoco.MjData(model)
    qadr = model.jnt_qposadr[model.joint(JOINT).id]
    angle0 = math.radians(angle0_deg)
    data.qpos[qadr] = angle0
    servo = model.actuator(SERVO).id
    muscles = [model.actuator(m).id for m in MUSCLES]
    prosthesis = isinstance(env.unwrapped, ProsthesisElbowEnv)
    if prosthesis:
        data.ctrl[servo] = angle0
    mujoco.mj_forward(model, data)

    def forces():
        if not prosthesis:
            return -data.actuator_force[muscles]
        tau = data.actuator_force[servo]
        arms = moment_arms_exact_m([data.qpos[qadr]], model)[0]
        return np.array([max(tau, 0) / arms[0], max(-tau, 0) / -arms[1]])

    t, f = [data.time], [forces()]
    for a in actions:
        if prosthesis:
            data.ctrl[servo] = math.radians(65 + 65 * float(a[0]))
        else:
            data.ctrl[muscles] = a
        for _ in range(env.unwrapped.frame_skip):
            mujoco.mj_step(model, data)
            mujoco.mj_forward(model, data)
            t.append(data.time)
            f.append(forces())
    return np.array(t), np.array(f)


@pytest.mark.parametrize("env_cls", [ElbowReachEnv, ProsthesisElbowEnv])
def test_ib_is_the_reference_solver_on_independently_replayed_forces(env_cls):
    env = env_cls(include_ib=True, afferent_source="reduced")
    actions = actions_for(env, 20)
    obs, infos = rollout(env, actions, seed=4)
    t, f = replay_forces(env, actions, infos[0]["angle_deg"])
    skip = env.frame_skip
    force_env = np.array([i["force_N"] for i in infos])
    # the env's forces are MuJoCo's (muscles: the same numbers, measured 0; the servo's
    # split by the 0.5 deg table against the exact moment arms: measured 6.7e-6 relative)
    prosthesis = env_cls is ProsthesisElbowEnv
    np.testing.assert_allclose(force_env, f[::skip], rtol=2e-5 if prosthesis else 1e-9,
                               atol=1e-6)
    assert f.max() > 50.0  # the muscles or the servo pulled: a test that can fail
    ref = np.stack([reference_rates(lambda s, j=j: np.interp(s, t, f[:, j]), t, G2[j], HUMAN)
                    for j in range(2)], axis=1)
    ib = np.array([i["ib_pps"] for i in infos])
    # the exact step on a force linear between physics steps: measured 2.1e-4 pps
    # (muscles); 0.074 pps (servo: its torque jumps to the 20 N m limit within one 2 ms
    # physics step at a new command, 0 -> 1000 N, the log's curvature over a jump)
    np.testing.assert_allclose(ib, ref[::skip], atol=0.1 if prosthesis else 5e-4)
    np.testing.assert_allclose(obs[:, 5:7] * RATE_SCALE_PPS, ib, rtol=1e-6, atol=1e-5)
    assert np.all(ib >= 0) and ib.max() > 5.0


@pytest.mark.parametrize("env_id", V1)
def test_v1_is_v0_plus_ib(env_id):
    v0 = gym.make(env_id.replace("-v1", "-v0"), include_fusimotor=True)
    v1 = gym.make(env_id, include_fusimotor=True)
    assert v0.observation_space.shape == (9,) and v1.observation_space.shape == (11,)
    actions = actions_for(v0, 15)
    o0, i0 = rollout(v0, actions, seed=2)
    o1, i1 = rollout(v1, actions, seed=2)
    np.testing.assert_array_equal(o1[:, :5], o0[:, :5])
    np.testing.assert_array_equal(o1[:, 7:], o0[:, 5:])
    ib = np.array([i["ib_pps"] for i in i1])
    np.testing.assert_array_equal(o1[:, 5:7], (ib / RATE_SCALE_PPS).astype(np.float32))
    assert "ib_pps" not in i0[-1] and "force_N" not in i0[-1]
    assert i1[-1]["force_N"].shape == (2,) and v1.observation_space.contains(o1[-1])


@pytest.mark.parametrize("env_id", V1)
def test_numpy_and_c_ib_agree(env_id):
    envs = [gym.make(env_id, backend=b, afferent_source="reduced") for b in ("numpy", "c")]
    actions = actions_for(envs[0], 30)
    ib = [np.array([i["ib_pps"] for i in rollout(e, actions, seed=8)[1]]) for e in envs]
    assert envs[1].unwrapped.tendon_organs.backend == "c"
    assert np.abs(ib[0] - ib[1]).max() <= 1e-9  # measured 1.4e-14 pps
    assert ib[0].max() > 5.0


@pytest.mark.parametrize("backend", ["numpy", "c"])
@pytest.mark.parametrize("env_id", V1)
def test_v1_sub_env_equals_single_env_through_autoresets(env_id, backend):
    err, resets = compare_with_singles(env_id, 2, 11, 4, afferent_source="reduced",
                                       backend=backend)
    assert resets == 4 and err <= 1e-6


def test_v1_vector_info_has_forces_and_ib():
    venv = gym.make_vec(V1[0], num_envs=3)
    _, info = venv.reset(seed=0)
    _, _, _, _, info = venv.step(np.full((3, 2), 0.7, np.float32))
    assert info["force_N"].shape == (3, 2) and info["ib_pps"].shape == (3, 2)
    assert np.all(info["ib_pps"] > 0)
    venv.close()


@pytest.mark.parametrize("backend", ["numpy", "c"])
def test_copies_of_a_v1_env_continue_identically(backend):
    env = gym.make(V1[1], backend=backend)
    env.reset(seed=1)
    for a in actions_for(env, 5):
        env.step(a)
    copies = [pickle.loads(pickle.dumps(env)), copy.deepcopy(env)]
    for a in actions_for(env, 5, seed=9):
        want = env.step(a)[0]
        for c in copies:
            np.testing.assert_array_equal(c.step(a)[0], want)


def test_non_finite_and_huge_forces_follow_the_counted_rule():
    sense = TendonForceSense(2, 2e-3, np.array([987.26, 624.3]), "numpy")
    sense.reset(np.arange(2), np.array([[10.0, 0.0], [20.0, 5.0]]))
    f = np.full((2, 3, 2), 100.0)
    f[0, 1, 0] = np.nan
    f[1, 0, 1] = np.inf
    f[1, 2, 0] = 1e9
    ib = sense.step(f)
    assert np.all(np.isfinite(ib)) and np.all(ib >= 0)
    assert sense.held.tolist() == [1, 1] and sense.clamped.tolist() == [0, 1]
    assert sense.force_N[1, 0] == MAX_FORCE_N
    # the held samples are the previous ones: the same as stepping those values
    g = f.copy()
    g[0, 1, 0], g[1, 0, 1], g[1, 2, 0] = 100.0, 5.0, MAX_FORCE_N
    other = TendonForceSense(2, 2e-3, np.array([987.26, 624.3]), "numpy")
    other.reset(np.arange(2), np.array([[10.0, 0.0], [20.0, 5.0]]))
    np.testing.assert_array_equal(other.step(g), ib)


@pytest.mark.parametrize("env_id", V1)
def test_v1_passes_gymnasiums_env_checker_and_refuses_a_bad_flag(env_id):
    from gymnasium.utils.env_checker import check_env

    check_env(gym.make(env_id).unwrapped, skip_render_check=True)
    with pytest.raises(ValueError, match="include_ib"):
        gym.make(env_id, include_ib="no")
