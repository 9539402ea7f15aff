"""docs/envs.md: "a non-finite physics state or observation raises RuntimeError rather than
being returned", for both envs, single and native vector, every afferent source.

The faults are injected where they would arise, not in the env's own code: the physics
through ``mujoco.rollout.Rollout`` (what the envs step with), which leaves NaN positions and
velocities; the observation through the numpy chain's rate function, which returns a NaN Ia.
"""

from __future__ import annotations

import gymnasium as gym
import mujoco.rollout
import numpy as np
import pytest

import proprio_env  # noqa: F401  (registers the ids)
from spindle import core

ENV_IDS = ("proprio_env/ElbowReach-v0", "proprio_env/ProsthesisElbow-v0")


def make(env_id: str, vector: bool, **kwargs):
    if vector:
        return gym.make_vec(env_id, num_envs=2, **kwargs)
    return gym.make(env_id, **kwargs)


@pytest.fixture
def diverging_physics(monkeypatch):
    """Rollout whose steps, once ``armed``, end in a NaN state (the states it returns and the
    scratch data it leaves); ``calls`` counts the rollouts so the injection is seen to run."""
    fault = {"armed": False, "calls": 0}

    class Diverging(mujoco.rollout.Rollout):
        def rollout(self, models, data, *args, **kwargs):
            out = super().rollout(models, data, *args, **kwargs)
            fault["calls"] += 1
            if fault["armed"]:
                kwargs["state"][:, -1, 1:] = np.nan  # everything but the time
                for d in data:
                    d.qpos[:] = np.nan
                    d.qvel[:] = np.nan
            return out

    monkeypatch.setattr(mujoco.rollout, "Rollout", Diverging)
    return fault


@pytest.mark.parametrize("vector", [False, True])
@pytest.mark.parametrize("source", ["exact", "reduced", "encoder"])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_a_non_finite_physics_state_raises_runtime_error(diverging_physics, env_id, source,
                                                         vector):
    env = make(env_id, vector, afferent_source=source)
    env.reset(seed=0)
    obs = env.step(env.action_space.sample())[0]
    assert np.isfinite(obs).all() and diverging_physics["calls"] >= 1
    diverging_physics["armed"] = True
    with pytest.raises(RuntimeError, match=r"physics diverged.*elbow angle \S*nan"):
        env.step(env.action_space.sample())
    assert diverging_physics["calls"] >= 2


@pytest.mark.parametrize("vector", [False, True])
@pytest.mark.parametrize("env_id", ENV_IDS)
def test_a_non_finite_observation_raises_runtime_error(monkeypatch, env_id, vector):
    env = make(env_id, vector, backend="numpy")
    env.reset(seed=0)
    rates = core.afferents_from_tension
    poisoned = []

    def nan_ia(*args, **kwargs):
        ia, ii = rates(*args, **kwargs)
        poisoned.append(ia.size)
        return np.full_like(ia, np.nan), ii

    monkeypatch.setattr(core, "afferents_from_tension", nan_ia)
    with pytest.raises(RuntimeError, match=r"non-finite observation \[nan, nan,"):
        env.step(env.action_space.sample())
    assert poisoned
