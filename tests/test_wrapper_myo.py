"""The spindle-afferent wrappers on myo-sim's published models (the ``myo`` extra)."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest

pytest.importorskip("myo_sim", reason="myo-sim is not installed (the 'myo' extra: "
                    "pip install --no-deps myo-sim==0.2.4)")
pytest.importorskip("imageio", reason="gymnasium.envs.mujoco needs imageio")

from proprio_env.wrappers import SpindleAfferents, SpindleAfferentsVector
from proprio_env.wrappers.mjcf_env import MuscleModelEnv, myo_sim_model_path

MAX_RATE_PPS = {"elbow": 120.0, "legs_osl": 520.0}
"""Bound of the soak's rates, per model, just above the highest measured (2026-12-02, seeded
controls, 10^5 env steps): elbow 109.5 pps (numpy) / 109.7 (C lagged), legs 478.2 / 499.8
(unseeded runs reached 640). Human afferents fire below ~300 pps in recordings; the legs'
random maximal controls lengthen fibres at up to the 8 L0/s limit and drive the model above
that, so the legs' bound is the model's, not physiology's."""

MODELS = {"elbow": 6, "legs_osl": 54}


def make(name: str, episode_steps: int = 100):
    path = myo_sim_model_path(name)
    model = mujoco.MjModel.from_xml_path(str(path))  # compiled once, copied by each env
    return lambda: gym.wrappers.TimeLimit(
        MuscleModelEnv(path, frame_skip=10, model=model), max_episode_steps=episode_steps)


def soak(name: str, steps: int, n_envs: int, **wrapper_args) -> dict[str, float]:
    """Random controls through the vector wrapper; every afferent checked at every step."""
    vec = SpindleAfferentsVector(gym.vector.SyncVectorEnv([make(name)] * n_envs),
                                 **wrapper_args)
    assert vec.muscles.n == MODELS[name]
    obs, _ = vec.reset(seed=0)
    vec.action_space.seed(0)  # the same controls every run: the highest rate is reproducible
    space = vec.single_observation_space
    highest = 0.0
    for _ in range(steps // n_envs):
        obs, _, _, _, info = vec.step(vec.action_space.sample())
        ia, ii = info["spindle_ia_pps"], info["spindle_ii_pps"]
        assert np.all(np.isfinite(obs))
        assert ia.min() >= 0 and ii.min() >= 0
        highest = max(highest, ia.max(), ii.max())
        assert highest <= MAX_RATE_PPS[name]
        lengths = info["spindle_length_L0"]
        assert lengths.min() >= 0.5 and lengths.max() <= 1.5
    assert all(space.contains(o) for o in obs)
    return {"highest_pps": highest, "clamped": int(info["spindle_length_clamped"].sum()),
            "restarts": info["spindle_restarts"]}


@pytest.mark.parametrize("name", sorted(MODELS))
def test_random_controls_give_finite_bounded_afferents(name):
    soak(name, steps=240, n_envs=4)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_single_wrapper_records_every_physics_step(name):
    """Every physics step of every env step reaches the spindles: the records the wrapper
    takes hold frame_skip rows per env step, whose times and actuator lengths and velocities
    (every actuator; the wrapper picks its muscles from them) are those of
    an independent replay (the env's whole integration state copied into a shadow MjData,
    stepped one mj_step at a time and read back after each), bit for bit."""
    env = SpindleAfferents(make(name)())
    assert env.substep_source == "frames"
    base = env.unwrapped
    model, data = base.model, base.data
    taken = []
    take = env.tap.records

    def spy():
        records = take()
        taken.append(tuple(np.copy(r) for r in records))  # views: valid until the next step
        return records

    env.tap.records = spy
    obs, info = env.reset(seed=1)
    assert obs.shape == (base.observation_space.shape[0] + 2 * MODELS[name],)
    shadow = mujoco.MjData(model)
    spec = mujoco.mjtState.mjSTATE_INTEGRATION
    state = np.empty(mujoco.mj_stateSize(model, spec))
    steps = 8
    for _ in range(steps):
        action = env.action_space.sample()
        mujoco.mj_getState(model, data, state, spec)
        before = len(taken)
        obs, _, _, _, info = env.step(action)
        assert len(taken) == before + 1  # one take per env step
        # the replay: the state before the step, the ctrl the env applied
        mujoco.mj_setState(model, shadow, state, spec)
        shadow.ctrl[:] = data.ctrl
        want = []
        for _ in range(base.frame_skip):
            t = shadow.time
            mujoco.mj_step(model, shadow)
            want.append((t, shadow.actuator_length.copy(), shadow.actuator_velocity.copy()))
        times, lengths, velocities = taken[-1]
        assert len(times) == base.frame_skip == 10
        np.testing.assert_array_equal(times, [w[0] for w in want])
        np.testing.assert_array_equal(lengths, [w[1] for w in want])
        np.testing.assert_array_equal(velocities, [w[2] for w in want])
        assert shadow.time == data.time
        np.testing.assert_array_equal(shadow.qpos, data.qpos)
        assert info["spindle_substep_source"] == "frames"
        assert np.all(np.isfinite(obs))
    assert sum(len(r[0]) for r in taken[1:]) == steps * base.frame_skip


def test_legs_name_their_muscles_and_skip_the_prosthesis_motors():
    env = SpindleAfferents(make("legs_osl")())
    names = env.muscle_names
    assert len(names) == 54
    assert not any(n.startswith("osl_") for n in names)
    one = SpindleAfferents(make("legs_osl")(), muscles=[names[3], names[0]])
    _, info = one.reset(seed=0)
    assert one.muscle_names == (names[3], names[0])
    assert info["spindle_ia_pps"].shape == (2,)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(MODELS))
def test_soak_1e5_steps(name):
    """10^5 env steps of random controls (16 envs), episodes of 100 steps."""
    result = soak(name, steps=100_000, n_envs=16)
    assert result["restarts"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(MODELS))
def test_soak_1e5_steps_c_lagged(name):
    """The same soak on the fast configuration: the C batch step (SIMD lanes where the CPU
    has them), afferents lagging one physics step."""
    from spindle.chain import resolve_backend

    if resolve_backend("auto") != "c":
        pytest.skip("no C compiler or cached C build")
    result = soak(name, steps=100_000, n_envs=16, backend="c", lag_physics_step=True)
    assert result["restarts"] == 0


def test_legs_c_backend_equals_numpy_backend():
    """All 54 leg muscles of two envs on the C batch step and on the numpy core, under
    random controls (many lengths clamped at the ends of the range): rates within 1e-9 pps."""
    from spindle.chain import resolve_backend

    if resolve_backend("auto") != "c":
        pytest.skip("no C compiler or cached C build")
    vecs = {b: SpindleAfferentsVector(gym.vector.SyncVectorEnv([make("legs_osl")] * 2),
                                      backend=b) for b in ("numpy", "c")}
    for v in vecs.values():
        v.reset(seed=3)
    rng = np.random.default_rng(2)
    space = vecs["c"].action_space
    worst = 0.0
    for _ in range(25):
        a = rng.uniform(space.low, space.high).astype(np.float32)
        infos = {b: v.step(a)[4] for b, v in vecs.items()}
        for key in ("spindle_ia_pps", "spindle_ii_pps"):
            worst = max(worst, np.abs(infos["c"][key] - infos["numpy"][key]).max())
    assert infos["c"]["spindle_length_clamped"].sum() > 0
    assert worst <= 1e-9
