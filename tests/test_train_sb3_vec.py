"""SB3VectorEnv (proprio_env/training/sb3_vec.py): a Gymnasium vector env that autoresets on
the next step, seen by stable-baselines3 as a VecEnv. Reference: SB3's own DummyVecEnv over single
envs, fed the same seeds and actions (it resets an ended env in the same step, the
convention the adapter converts to)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import DummyVecEnv

import proprio_env
from proprio_env.training.sb3_vec import SB3VectorEnv, unbatch_info


def assert_same_steps(adapter, reference, actions, atol=0.0):
    """Step both with the same actions; compare every output, infos included."""
    ended = 0
    for t, action in enumerate(actions):
        got, want = adapter.step(action), reference.step(action)
        for name, a, b in zip(("obs", "reward", "done"), got[:3], want[:3], strict=True):
            np.testing.assert_allclose(a, b, atol=atol, rtol=0, err_msg=f"{name}, step {t}")
        for i, (a, b) in enumerate(zip(got[3], want[3], strict=True)):
            assert set(a) == set(b), (t, i, sorted(a), sorted(b))
            for key in a:
                np.testing.assert_allclose(np.asarray(a[key], dtype=float),
                                           np.asarray(b[key], dtype=float), atol=atol, rtol=0,
                                           err_msg=f"info[{key!r}], env {i}, step {t}")
        ended += int(np.sum(got[2]))
    return ended


def test_episodes_ending_at_different_steps_match_dummy_vec_env():
    # CartPole's episodes end at different steps in different sub-envs: partial resets
    n = 4
    adapter = SB3VectorEnv(gym.make_vec("CartPole-v1", num_envs=n, vectorization_mode="sync"))
    reference = DummyVecEnv([lambda: gym.make("CartPole-v1") for _ in range(n)])
    adapter.seed(3)
    reference.seed(3)
    np.testing.assert_array_equal(adapter.reset(), reference.reset())
    actions = np.random.default_rng(0).integers(0, 2, (300, n))
    ended = assert_same_steps(adapter, reference, actions)
    assert ended > 20  # many partial resets happened


@pytest.mark.parametrize("env_id", sorted(proprio_env.ENV_IDS))
def test_our_vector_env_matches_single_envs_through_truncation(env_id):
    n, steps = 3, 5
    adapter = SB3VectorEnv(gym.make_vec(env_id, num_envs=n, max_episode_steps=steps,
                                        backend="c"))
    reference = DummyVecEnv([lambda: gym.make(env_id, max_episode_steps=steps, backend="c")
                             for _ in range(n)])
    adapter.seed(11)
    reference.seed(11)
    np.testing.assert_allclose(adapter.reset(), reference.reset(), atol=1e-6, rtol=0)
    space = reference.action_space
    actions = np.random.default_rng(1).uniform(space.low, space.high, (2 * steps + 2, n,
                                                                       *space.shape))
    ended = assert_same_steps(adapter, reference, actions.astype(np.float32), atol=1e-6)
    assert ended == 2 * n  # every env truncated twice, and the reset obs came back at once


def test_terminal_observation_and_time_limit_flag():
    adapter = SB3VectorEnv(gym.make_vec("proprio_env/ElbowReach-v0", num_envs=2,
                                        max_episode_steps=2, backend="c"))
    adapter.seed(0)
    first = adapter.reset()
    zero = np.zeros((2, 2), dtype=np.float32)
    obs, _, done, infos = adapter.step(zero)
    assert not done.any() and not infos[0]["TimeLimit.truncated"]
    obs, _, done, infos = adapter.step(zero)
    assert done.all()
    for i in range(2):
        assert infos[i]["TimeLimit.truncated"]
        # the returned obs is the new episode's, the last one is in terminal_observation
        assert not np.array_equal(infos[i]["terminal_observation"], obs[i])
        assert infos[i]["terminal_observation"].shape == first[i].shape
    assert adapter.reset_infos[0]["sensor_samples"] == 0  # the reset's info


def test_refuses_same_step_autoreset_and_per_env_options():
    venv = gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync",
                        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP})
    with pytest.raises(ValueError, match="autoreset_mode"):
        SB3VectorEnv(venv)
    adapter = SB3VectorEnv(gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync"))
    adapter.set_options([{"a": 1}, {"a": 2}])
    with pytest.raises(ValueError, match="one options dict"):
        adapter.reset()
    with pytest.raises(ValueError, match="indices=None"):
        adapter.set_attr("x", 1, indices=[0])


def test_unbatch_info_follows_the_masks():
    info = {"a": np.array([1.0, 2.0, 3.0]), "_a": np.array([True, False, True]),
            "b": {"c": np.array([4, 5, 6]), "_c": np.array([False, True, False])},
            "_b": np.array([True, True, False])}
    assert unbatch_info(info, 3) == [{"a": 1.0, "b": {}}, {"b": {"c": 5}}, {"a": 3.0}]
