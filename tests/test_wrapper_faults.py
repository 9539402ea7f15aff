"""Faults of the spindle-afferent wrappers (issue 28, items 3-6): copies of wrapped envs,
the bound on the work per interval, SAME_STEP autoreset, wrappers stacked on one env.

Each test compares with an independent run: a wrapper that was never copied, a lone wrapper
per muscle set, a single wrapped env run to the same end, the spindle's closed-form rest
state (``spindle.core.equilibrium_state``), or the counted work."""

from __future__ import annotations

import copy
import functools
import pickle

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

from proprio_env.body.model import MUSCLES, model_path
from proprio_env.wrappers import SpindleAfferents, SpindleAfferentsVector, capture, find_muscles
from proprio_env.wrappers import trajectory as trajectory_module
from proprio_env.wrappers.trajectory import MAX_TRAJECTORY_SUBSTEPS, afferents_from_trajectory
from spindle import core
from spindle.backends import resolve_backend
from spindle.chain import bank as bank_module
from spindle.params import HUMAN

pytest.importorskip("imageio", reason="gymnasium.envs.mujoco needs imageio")
from proprio_env.wrappers.mjcf_env import MuscleModelEnv

SERVO_OFF = 1 << 2  # actuator group 2: the elbow's position servo
NEEDS_C = pytest.mark.skipif(resolve_backend("auto") != "c",
                             reason="no C compiler or cached C build")
BACKENDS = ["numpy", pytest.param("c", marks=NEEDS_C)]


def elbow_env() -> MuscleModelEnv:
    """Module level, so that a vector env of these pickles."""
    env = MuscleModelEnv(model_path(), frame_skip=10)
    env.model.opt.disableactuator = SERVO_OFF
    return env


def short_episodes() -> gym.Env:
    return gym.wrappers.TimeLimit(elbow_env(), max_episode_steps=6)


def actions(n_steps: int, n_envs: int | None = None, seed: int = 0) -> np.ndarray:
    shape = (n_steps, 3) if n_envs is None else (n_steps, n_envs, 3)
    a = np.random.default_rng(seed).uniform(0.0, 1.0, shape).astype(np.float32)
    a[..., 2] = 0.0
    return a


def rest_rates(length_L0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ia, II of spindles at equilibrium at ``length_L0`` under the default drive."""
    return core.afferents(core.equilibrium_state(np.asarray(length_L0, float), 100.0, 85.0,
                                                 HUMAN), HUMAN)


def assert_same_step(a, b) -> None:
    """Two wrapped steps' outputs equal bit for bit (observation, reward, flags, arrays of
    info)."""
    for x, y in zip(a[:4], b[:4], strict=True):
        np.testing.assert_array_equal(x, y)
    for key, value in a[4].items():
        if key.startswith("spindle_"):
            np.testing.assert_array_equal(value, b[4][key], err_msg=key)


def duplicate(env, how: str):
    return copy.deepcopy(env) if how == "deepcopy" else pickle.loads(pickle.dumps(env))


# -- 28.3: copies ------------------------------------------------------------------------

@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
@pytest.mark.parametrize("lag", [False, True])
def test_a_copy_mid_episode_continues_bit_for_bit_as_an_uncopied_wrapper(backend, how, lag):
    """A wrapper copied after 7 steps, and its original, each stepped on with the same
    actions (the copy first, for several steps, so that shared state would show), equal a
    wrapper on its own env that was never copied, bit for bit."""
    a = actions(20)
    reference, original = (SpindleAfferents(elbow_env(), backend=backend, lag_physics_step=lag)
                           for _ in range(2))
    for env in (reference, original):
        env.reset(seed=5)
    for i in range(7):
        assert_same_step(reference.step(a[i]), original.step(a[i]))
    clone = duplicate(original, how)
    assert clone.substep_source == "frames" and clone.bank.backend == backend
    from_clone = [clone.step(a[i]) for i in range(7, 20)]
    from_original = [original.step(a[i]) for i in range(7, 20)]
    for i, (x, y) in enumerate(zip(from_clone, from_original, strict=True)):
        want = reference.step(a[7 + i])
        assert_same_step(x, want)
        assert_same_step(y, want)
        assert x[4]["spindle_substep_source"] == "frames"
    assert max(s[4]["spindle_ia_pps"].max() for s in from_clone) > 20.0  # they move


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("how", ["deepcopy", "pickle"])
@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_a_copied_vector_wrapper_continues_bit_for_bit(backend, how, mode):
    n, a = 3, actions(16, 3, seed=1)
    reference, original = (SpindleAfferentsVector(gym.vector.SyncVectorEnv(
        [short_episodes] * n, autoreset_mode=mode), backend=backend) for _ in range(2))
    for env in (reference, original):
        env.reset(seed=2)
    for i in range(4):
        assert_same_step(reference.step(a[i]), original.step(a[i]))
    clone = duplicate(original, how)
    from_clone = [clone.step(a[i]) for i in range(4, 16)]  # crosses the autoresets
    for i in range(4, 16):
        want = reference.step(a[i])
        assert_same_step(from_clone[i - 4], want)
        assert_same_step(original.step(a[i]), want)
        if "final_obs" in want[4]:
            for x, y in zip(from_clone[i - 4][4]["final_obs"], want[4]["final_obs"],
                            strict=True):
                assert (x is None and y is None) or np.array_equal(x, y)
    assert mode != AutoresetMode.SAME_STEP or all(
        isinstance(e.__dict__["reset"], type(original._final_hooks[0])) and
        e.__dict__["reset"].tap is tap for e, tap in zip(clone.env.envs, clone.taps,
                                                         strict=True))


# -- 28.4: bounded work ------------------------------------------------------------------

@pytest.fixture
def substep_count(monkeypatch):
    """Counts the spindle sub-steps the banks take (rows of the sub-step lengths)."""
    counted = []
    real = bank_module.substep_lengths

    def counting(*args, **kwargs):
        out = real(*args, **kwargs)
        counted.append(out[0].shape[0])
        return out

    monkeypatch.setattr(bank_module, "substep_lengths", counting)
    return counted


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_clock_jump_restarts_the_spindles_at_rest_with_bounded_work(backend, substep_count):
    """data.time set forward by 3 s to 1e300 s (or to inf/NaN) between steps: the next step
    restarts the spindles at rest at the env's lengths (the closed-form equilibrium), counted
    once, and takes no more sub-steps than an ordinary step (20); the steps after go on from
    there."""
    env = SpindleAfferents(elbow_env(), backend=backend)
    env.reset(seed=1)
    data = env.unwrapped.data
    a = actions(40)
    for i, jump in enumerate([3.0, 1e6, 1e300, np.inf, -np.inf, np.nan]):
        env.step(a[2 * i])
        restarts = env.bank.restarts
        substep_count.clear()
        data.time = data.time + jump if np.isfinite(jump) else jump
        obs, _, _, _, info = env.step(a[2 * i + 1])
        assert sum(substep_count) == 0, (jump, substep_count)
        assert info["spindle_restarts"] == restarts + 1
        ia, ii = rest_rates(info["spindle_length_L0"])
        np.testing.assert_allclose(info["spindle_ia_pps"], ia, rtol=0, atol=1e-9)
        np.testing.assert_allclose(info["spindle_ii_pps"], ii, rtol=0, atol=1e-9)
        assert np.all(np.isfinite(obs))
        if not np.isfinite(data.time):
            data.time = 0.0
            env.step(a[2 * i])  # time ran back from inf: another restart
    substep_count.clear()
    info = env.step(a[-1])[4]
    assert sum(substep_count) == 20 and info["spindle_substep_source"] == "frames"


def test_a_jump_within_the_limit_is_carried_with_its_knots_and_the_limit_is_an_argument(
        substep_count):
    """A forward jump shorter than max_interval_s is bridged by the Hermite curve (a knot
    per physics step: 0.5 s / 2 ms = 250 knots, 500 sub-steps of 1 ms); with max_interval_s
    0.1 the same jump restarts."""
    for limit, restarted in ((1.0, False), (0.1, True)):
        env = SpindleAfferents(elbow_env(), max_interval_s=limit)
        env.reset(seed=0)
        env.step(actions(1)[0])
        env.unwrapped.data.time += 0.48
        substep_count.clear()
        info = env.step(actions(1)[0])[4]
        assert info["spindle_restarts"] == int(restarted)
        assert sum(substep_count) == (0 if restarted else 500)
        assert info["spindle_substep_source"] == ("frames" if restarted else "hermite")
        assert env.substep_source == info["spindle_substep_source"]


def test_an_env_stepped_for_long_without_its_wrapper_keeps_bounded_records(substep_count):
    """10^4 physics steps through env.unwrapped (the wrapper not called): the recorder keeps
    at most one restart interval of records (1 s / 2 ms + 2), and the next wrapped step
    restarts (counted) instead of integrating 20 s of motion."""
    env = SpindleAfferents(elbow_env())
    env.reset(seed=0)
    for i in range(1000):
        env.unwrapped.step(actions(1, seed=i)[0])
    recorder = env.tap.recorder
    assert recorder._count == recorder.max_records == 502
    assert recorder.dropped == 10_000 - 502
    substep_count.clear()
    info = env.step(actions(1)[0])[4]
    assert info["spindle_restarts"] == 1 and sum(substep_count) == 0


def test_vector_sub_env_whose_clock_jumps_restarts_alone():
    """One sub-env's clock set forward by 0.1 s (within the limit, but unlike the others') and
    another's by 1e9 s: those two restart at rest (counted); the third goes on exactly as a
    single wrapper on the same seed and actions."""
    n, a = 3, actions(12, 3, seed=2)
    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv([elbow_env] * n))
    single = SpindleAfferents(elbow_env())
    vec.reset(seed=7)
    single.reset(seed=9)
    for i in range(12):
        if i == 5:
            vec.env.envs[0].unwrapped.data.time += 0.1
            vec.env.envs[1].unwrapped.data.time += 1e9
        _, _, _, _, info = vec.step(a[i])
        info_s = single.step(a[i][2])[4]
        np.testing.assert_allclose(info["spindle_ia_pps"][2], info_s["spindle_ia_pps"],
                                   rtol=0, atol=1e-9)
        if i == 5:
            assert info["spindle_restarts"] == 2
            for row in (0, 1):
                ia, _ = rest_rates(info["spindle_length_L0"][row])
                np.testing.assert_allclose(info["spindle_ia_pps"][row], ia, atol=1e-9)
    assert info["spindle_restarts"] == 2 and info["spindle_substep_source"] == "frames"


def test_max_interval_is_checked():
    for bad in (0.0, 1e-4, -1.0, np.nan, np.inf, True, "1.0", 1 + 0j, None):
        with pytest.raises(ValueError, match="max_interval_s"):
            SpindleAfferents(elbow_env(), max_interval_s=bad)
    with pytest.raises(ValueError, match=r"shorter than the env step 0\.02"):
        SpindleAfferents(elbow_env(), max_interval_s=0.01)
    with pytest.raises(ValueError, match="MAX_SUBSTEPS = 100000"):
        SpindleAfferents(elbow_env(), max_interval_s=101.0)
    with pytest.raises(ValueError, match="max_interval_s"):
        SpindleAfferentsVector(gym.vector.SyncVectorEnv([elbow_env] * 2), max_interval_s=0.0)


def test_a_trajectory_in_milliseconds_is_refused_before_any_work(monkeypatch):
    """Times in ms read as s: 2000 samples 1 s apart need 1.999e6 sub-steps, refused with the
    count and the limit when above max_substeps; 10 s apart (1e4 sub-steps per interval) is
    within one interval's limit; 1000 s apart (1e6) is not. No kinematics is computed."""
    calls = []
    monkeypatch.setattr(trajectory_module.ActuatorKinematics, "compute",
                        lambda *a, **k: calls.append(1))
    model = elbow_env().model
    q = np.full((2000, model.nq), 1.0)
    with pytest.raises(ValueError, match=r"needs 1999000 spindle sub-steps .* max_substeps "
                                         r"= 1000000"):
        afferents_from_trajectory(model, q, np.arange(2000.0), max_substeps=1_000_000)
    with pytest.raises(ValueError, match=f"max_substeps = {MAX_TRAJECTORY_SUBSTEPS}"):
        afferents_from_trajectory(model, q, 10.0 * np.arange(2000))
    with pytest.raises(ValueError, match=r"needs 1000000 spindle sub-steps .* MAX_SUBSTEPS"):
        afferents_from_trajectory(model, q[:3], 1000.0 * np.arange(3))
    for bad in (0, -1, 2.5, True, "10"):
        with pytest.raises(ValueError, match="max_substeps"):
            afferents_from_trajectory(model, q[:3], np.arange(3) * 1e-3, max_substeps=bad)
    assert calls == []


def test_a_trajectory_is_advanced_in_chunks_of_bounded_sub_steps(substep_count):
    """50 ms samples (50 sub-steps each): every batched advance holds at most
    CHUNK_SUBSTEPS sub-steps, and the result equals one taken in chunks of one sample."""
    model = elbow_env().model
    t = np.arange(400) * 0.05
    q = (1.2 + 0.8 * np.sin(2 * np.pi * 0.3 * t))[:, None]
    out = afferents_from_trajectory(model, q, t)
    assert max(substep_count) <= trajectory_module.CHUNK_SUBSTEPS
    assert sum(substep_count) == 399 * 50
    chunked = pytest.MonkeyPatch()
    chunked.setattr(trajectory_module, "CHUNK_SUBSTEPS", 1)
    try:
        one_by_one = afferents_from_trajectory(model, q, t)
    finally:
        chunked.undo()
    # each chunk takes its interval from its first sample's time: rounding only (3.9e-13
    # measured)
    np.testing.assert_allclose(out.ia_pps, one_by_one.ia_pps, rtol=0, atol=2e-12)


# -- 28.5: SAME_STEP autoreset -----------------------------------------------------------

@pytest.mark.parametrize("lag", [False, True])
@pytest.mark.parametrize("backend", BACKENDS)
def test_same_step_autoreset_gives_the_final_step_afferents(lag, backend):
    """SAME_STEP: final_obs of the step that ends an episode is the wrapped observation (in
    the wrapped space) with the afferents of that step, equal to a single wrapped env run to
    the same end; final_info has its spindle keys; the returned observation rests at the
    reset lengths; the next episode goes on as the single env's after its reset()."""
    n, steps = 2, 15
    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv(
        [short_episodes] * n, autoreset_mode=AutoresetMode.SAME_STEP), lag_physics_step=lag,
        backend=backend)
    singles = [SpindleAfferents(short_episodes(), lag_physics_step=lag, backend=backend)
               for _ in range(n)]
    vec.reset(seed=3)
    for i, s in enumerate(singles):
        s.reset(seed=3 + i)
    a = actions(steps, n, seed=4)
    ends = 0
    for k in range(steps):
        obs, _, _, trunc, info = vec.step(a[k])
        for i, s in enumerate(singles):
            obs_s, _, _, trunc_s, info_s = s.step(a[k][i])
            assert trunc[i] == trunc_s
            if not trunc_s:
                np.testing.assert_allclose(obs[i], obs_s, rtol=0, atol=1e-9)
                continue
            ends += 1
            final = info["final_obs"][i]
            assert vec.single_observation_space.contains(final)
            np.testing.assert_allclose(final, obs_s, rtol=0, atol=1e-9)
            assert info["final_info"]["_spindle_ia_pps"][i]
            np.testing.assert_allclose(info["final_info"]["spindle_ia_pps"][i],
                                       info_s["spindle_ia_pps"], rtol=0, atol=1e-9)
            obs_s, info_s = s.reset()
            np.testing.assert_allclose(obs[i], obs_s, rtol=0, atol=1e-9)
            ia, _ = rest_rates(info["spindle_length_L0"][i])
            np.testing.assert_allclose(info["spindle_ia_pps"][i], ia, rtol=0, atol=1e-9)
        assert np.all(np.isfinite(obs))
    assert ends == 2 * n
    vec.close()
    assert all("reset" not in e.__dict__ for e in vec.env.envs)


class RaisesOnce(gym.Wrapper):
    """Raises on its ``at``-th step, once (a sub-env failing inside the vector step)."""

    def __init__(self, env, at: int) -> None:
        super().__init__(env)
        self.at, self.count = at, 0

    def step(self, action):
        self.count += 1
        if self.count == self.at:
            raise RuntimeError("a sub-env failed")
        return self.env.step(action)


def test_same_step_with_a_sub_env_failing_after_another_ended_leaves_no_frozen_state():
    """Sub-env 0 ends (and is reset by the vector env) in the step where sub-env 1 raises:
    the wrapper's row 0 rests at its reset state (the closed-form rest), nothing is left
    frozen, and the next steps go on with every observation finite."""
    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv(
        [short_episodes, lambda: RaisesOnce(elbow_env(), 6)],
        autoreset_mode=AutoresetMode.SAME_STEP))
    vec.reset(seed=0)
    a = actions(10, 2)
    for k in range(5):
        vec.step(a[k])
    with pytest.raises(RuntimeError, match="a sub-env failed"):
        vec.step(a[5])
    assert all(tap.final is None for tap in vec.taps)
    assert vec.env.envs[0].unwrapped.data.time == 0.0  # reset by the vector env
    _, L, _ = vec.taps[0].now()
    ia, _ = rest_rates(np.clip(L, *core.LENGTH_RANGE_L0))
    np.testing.assert_allclose(vec.bank.ia_pps[0], ia, rtol=0, atol=1e-9)
    for k in range(6, 10):
        obs, *_ = vec.step(a[k])
        assert np.all(np.isfinite(obs))


# -- 28.6: wrappers stacked on one env ---------------------------------------------------

@pytest.mark.parametrize("lag", [False, True])
def test_two_wrappers_on_one_env_both_record_every_physics_step(lag):
    """SpindleAfferents(muscles=[BRA]) inside SpindleAfferents(muscles=[TRImed]) on one env:
    both use the recorded frames, and each equals a lone wrapper of its muscle on its own
    env, bit for bit. Closing the outer leaves the inner recording; closing both restores
    the env."""
    inner = SpindleAfferents(elbow_env(), muscles=[MUSCLES[0]], lag_physics_step=lag)
    outer = SpindleAfferents(inner, muscles=[MUSCLES[1]], lag_physics_step=lag)
    lone = [SpindleAfferents(elbow_env(), muscles=[m], lag_physics_step=lag) for m in MUSCLES]
    outer.reset(seed=6)
    for env in lone:
        env.reset(seed=6)
    a = actions(30, seed=6)
    for k in range(30):
        _, _, _, _, info_outer = outer.step(a[k])
        want = [env.step(a[k])[4] for env in lone]
        # the inner wrapper's info is what the outer one passed on, under the same keys;
        # read both from the banks
        np.testing.assert_array_equal(outer.bank.ia_pps[0], want[1]["spindle_ia_pps"])
        np.testing.assert_array_equal(inner.bank.ia_pps[0], want[0]["spindle_ia_pps"])
        np.testing.assert_array_equal(inner.bank.ii_pps[0], want[0]["spindle_ii_pps"])
        assert info_outer["spindle_substep_source"] == "frames"
        assert inner.substep_source == outer.substep_source == "frames"
    base = inner.unwrapped
    hook = base.__dict__[capture.HOOK_ATTRIBUTE]
    assert len(hook.recorders) == 2
    outer.tap.close()
    assert hook.installed() and len(hook.recorders) == 1
    inner.tap.close()
    assert "_step_mujoco_simulation" not in base.__dict__
    assert capture.HOOK_ATTRIBUTE not in base.__dict__


def test_a_replaced_physics_hook_is_never_a_silent_fallback():
    """A physics stepping replaced on the env instance by something else: auto takes the
    Hermite curve and says why, "frames" refuses; replaced after the wrapper was made, the
    next step reports "hermite" in substep_source and info."""
    env = elbow_env()
    env._step_mujoco_simulation = lambda ctrl, n: None
    w = SpindleAfferents(env)
    assert w.substep_source == "hermite" and "was replaced" in w.tap.why_hermite
    with pytest.raises(ValueError, match="was replaced"):
        SpindleAfferents(elbow_env_replaced(), substep_source="frames")
    w = SpindleAfferents(elbow_env())
    w.reset(seed=0)
    assert w.step(actions(1)[0])[4]["spindle_substep_source"] == "frames"
    base = w.unwrapped
    base._step_mujoco_simulation = type(base)._step_mujoco_simulation.__get__(base)
    info = w.step(actions(1)[0])[4]
    assert info["spindle_substep_source"] == w.substep_source == "hermite"
    assert np.all(np.isfinite(info["spindle_ia_pps"]))


def elbow_env_replaced() -> MuscleModelEnv:
    env = elbow_env()
    env._step_mujoco_simulation = lambda ctrl, n: None
    return env


# -- on myo-sim's models (the myo extra) -------------------------------------------------

@functools.cache
def myo_model(name: str):
    """myo-sim's model, compiled once (the compiler's lengthrange pass takes seconds)."""
    import mujoco

    from proprio_env.wrappers.mjcf_env import myo_sim_model_path

    return myo_sim_model_path(name), mujoco.MjModel.from_xml_path(str(myo_sim_model_path(name)))


def myo_env(name: str) -> gym.Env:
    path, model = myo_model(name)
    return MuscleModelEnv(path, frame_skip=10, model=model)


@pytest.mark.parametrize(("name", "backend"), [
    pytest.param("elbow", "c", marks=NEEDS_C),
    pytest.param("elbow", "numpy", marks=pytest.mark.slow),
    pytest.param("legs_osl", "numpy", marks=pytest.mark.slow),
    pytest.param("legs_osl", "c", marks=[pytest.mark.slow, NEEDS_C])])
def test_myo_copy_of_stacked_wrappers_continues_bit_for_bit(name, backend):
    """myo-sim's elbow (6 muscles; C by default, numpy slow) or legs with the OSL (54; slow:
    building and pickling the envs takes seconds), two
    wrappers stacked (half the muscles inside, the rest outside), pickled mid-episode: the
    copy, the original and an uncopied pair of wrappers agree bit for bit, all on recorded
    frames."""
    pytest.importorskip("myo_sim", reason="myo-sim is not installed: "
                        "pip install --no-deps myo-sim==0.2.4")

    def stacked():
        base = myo_env(name)
        names = find_muscles(base.model).names  # every muscle, in id order
        inner = SpindleAfferents(base, muscles=names[::2], backend=backend)
        return SpindleAfferents(inner, muscles=names[1::2], backend=backend), inner

    (reference, ref_inner), (original, inner) = stacked(), stacked()
    a = np.random.default_rng(0).uniform(0, 1, (12, original.action_space.shape[0]))
    for env in (reference, original):
        env.reset(seed=1)
    for k in range(4):
        assert_same_step(reference.step(a[k]), original.step(a[k]))
    clone = pickle.loads(pickle.dumps(original))
    clone_inner = clone.env
    for k in range(4, 12):
        want = reference.step(a[k])
        assert_same_step(clone.step(a[k]), want)
        assert_same_step(original.step(a[k]), want)
        for w in (clone_inner, inner):
            np.testing.assert_array_equal(w.bank.ia_pps, ref_inner.bank.ia_pps)
        assert clone.substep_source == clone_inner.substep_source == "frames"
    assert want[4]["spindle_ia_pps"].max() > 5.0
