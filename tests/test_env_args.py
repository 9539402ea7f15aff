"""The envs' arguments, reset options and actions refuse type confusion (a bool as a number, a
string as a bool or number, a complex number, an int beyond the float range) with a
ValueError naming the argument, and accept numpy scalars of the right kind."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import proprio_env  # noqa: F401  (registers the ids)

IDS = ("proprio_env/ElbowReach-v0", "proprio_env/ProsthesisElbow-v0")


def _id(value) -> str:
    text = repr(value)
    return text if len(text) <= 24 else f"{text[:8]}...({len(text)} chars)"


@pytest.mark.parametrize("env_id", IDS)
def test_numpy_scalars_are_accepted(env_id):
    env = gym.make(env_id, control_hz=np.float32(50), include_fusimotor=np.True_,
                   clip_actions=np.bool_(False), distance_reward_weight=np.float32(0.5),
                   control_cost_weight=np.int64(0), width=np.int64(64),
                   height=np.int32(48), target_ranges_deg=((np.float32(20), np.int16(30)),))
    obs, info = env.reset(seed=0, options={"angle_deg": np.float32(60)})
    assert env.unwrapped.dt == pytest.approx(0.02)  # 50 Hz
    assert obs.shape == (9,)  # fusimotor on
    assert 20.0 <= info["target_deg"] <= 30.0
    assert (env.unwrapped.width, env.unwrapped.height) == (64, 48)
    env.close()


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize(
    ("name", "value"),
    [
        # a bool is not a number
        ("control_hz", True),  # was 1 Hz
        ("width", True),
        ("height", np.False_),
        ("distance_reward_weight", True),
        ("control_cost_weight", np.True_),
        ("target_ranges_deg", ((True, 50.0),)),
        ("initial_angle_ranges_deg", ((False, 50.0),)),
        # a string is not a bool, nor a number
        ("include_fusimotor", "no"),  # was switched on
        ("clip_actions", "False"),
        ("include_fusimotor", 1),
        ("target_ranges_deg", (("10", "20"),)),
        ("distance_reward_weight", "1"),
        # complex numbers are not real
        ("control_hz", 50 + 0j),
        ("distance_reward_weight", np.complex128(1.0)),
        ("target_ranges_deg", ((np.complex64(10), 20.0),)),
        # ints beyond the float range (were OverflowError)
        ("control_hz", 10**400),
        ("control_cost_weight", 10**400),
        # out of the range of the argument
        ("control_hz", 1e-300),  # a 5e302-frame step
        ("width", 0),
        ("height", -5),
        ("width", 1.5),  # was truncated to 1
        ("width", "320"),
        ("height", 10**6),  # beyond the model's offscreen buffer (was a render-time error)
        # objects of the wrong type
        ("chain_config", "fast"),
        ("encoder_params", None),  # was an error at the first reset of the encoder source
        ("xml_file", 3),
    ],
    ids=_id,
)
def test_confused_argument_types_are_refused(env_id, name, value):
    with pytest.raises(ValueError, match=name):
        gym.make(env_id, **{name: value})


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("value", [True, "60", 60 + 0j, 10**400], ids=_id)
def test_confused_reset_options_are_refused(env_id, value):
    env = gym.make(env_id)
    for option in ("target_deg", "angle_deg"):
        with pytest.raises(ValueError, match=option):
            env.reset(seed=0, options={option: value})


def _bad_actions(n: int) -> list:
    return [
        np.full(n, 0.5 + 0.25j),  # was accepted, the imaginary part dropped
        np.full(n, 0.5, dtype=complex),  # a complex dtype is refused even with 0j
        ["0.5"] * n,  # strings
        [True] * n,  # bools
        [10**400] * n,  # beyond float (was OverflowError)
    ]


@pytest.mark.parametrize("env_id", IDS)
def test_non_real_actions_are_refused_and_change_nothing(env_id):
    env, twin = gym.make(env_id), gym.make(env_id)
    n = env.action_space.shape[0]
    env.reset(seed=4)
    twin.reset(seed=4)
    for bad in _bad_actions(n):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    good = np.full(n, 0.5, dtype=np.float32)
    obs, *_, info = env.step(good)
    obs_twin, *_, info_twin = twin.step(good)
    np.testing.assert_array_equal(obs, obs_twin)
    assert info["time_s"] == info_twin["time_s"]


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("seed", [1.5, np.float64(2.0), "3", b"3", True, np.True_, -1, [1],
                                  1 + 0j], ids=_id)
def test_confused_seeds_are_refused(env_id, seed):
    """A seed is None or an integer >= 0 (was gymnasium's own Error, or a float accepted)."""
    env = gym.make(env_id)
    with pytest.raises(ValueError, match=r"seed=.* must be None or an integer >= 0"):
        env.reset(seed=seed)


@pytest.mark.parametrize("env_id", IDS)
def test_refused_reset_changes_nothing(env_id):
    """A reset refused for its seed or any option leaves the episode and the generator as
    they were: the env steps on, and resets unseeded, as a twin that never saw it."""
    env, twin = gym.make(env_id), gym.make(env_id)
    env.reset(seed=4)
    twin.reset(seed=4)
    n = env.action_space.shape[0]
    refused = [
        {"seed": 5, "options": {"target_deg": "70"}},  # a good seed with a bad option
        {"seed": 6, "options": {"angle_deg": 500.0}},
        {"seed": 7, "options": {"target_deg": 40.0, "angle_deg": np.complex128(40)}},
        {"seed": 8, "options": {"speed": 1.0}},
        {"seed": 9, "options": {"angle_deg": [40.0]}},  # one env: a number, not a list
        {"seed": 10, "options": [("target_deg", 40.0)]},  # options are a dict
        {"seed": 2.5, "options": {"target_deg": 40.0}},
    ]
    for k, call in enumerate(refused):
        with pytest.raises(ValueError, match=r"seed|options|target_deg|angle_deg"):
            env.reset(**call)
        a = np.full(n, 0.1 * k, dtype=np.float32)
        obs, reward, *_, info = env.step(a)
        obs_twin, reward_twin, *_, info_twin = twin.step(a)
        assert obs.tobytes() == obs_twin.tobytes() and reward == reward_twin, call
        assert info["time_s"] == info_twin["time_s"], call
    assert env.reset()[0].tobytes() == twin.reset()[0].tobytes()
