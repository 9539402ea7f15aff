"""Soak (slow): long random-action runs stay finite and bounded; bad actions are rejected.

The full 10^6-step soak is ``python scripts/soak_env.py --steps 1000000``."""

from __future__ import annotations

import pytest

from proprio_env.experiments import soak as soak_env


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ["proprio_env/ElbowReach-v0",
                                    "proprio_env/ProsthesisElbow-v0"])
def test_random_actions_stay_finite_and_bounded(env_id):
    result = soak_env.soak(env_id, 10_000, seed=3)
    assert result["episodes"] == 10_000 // 200 + 1
    assert result["bad_actions_rejected"] == 2 * 10
    lo, hi = result["extremes"]["angle_deg"]
    assert -5 <= lo and hi <= 135


def test_soak_checker_catches_violations():
    import numpy as np

    info = {"angle_deg": 60.0, "angular_velocity_deg_s": 0.0, "ia_pps": np.array([10.0, 5.0]),
            "ii_pps": np.array([10.0, 5.0]), "gamma_static_pps": np.zeros(2),
            "gamma_dynamic_pps": np.zeros(2), "length_L0": np.array([1.0, 1.0])}
    soak_env.check_step(np.zeros(5, np.float32), info, (0, 130), 1)
    with pytest.raises(soak_env.SoakError, match="non-finite"):
        soak_env.check_step(np.array([np.nan] * 5), info, (0, 130), 1)
    with pytest.raises(soak_env.SoakError, match="angle"):
        soak_env.check_step(np.zeros(5), {**info, "angle_deg": 200.0}, (0, 130), 1)


@pytest.mark.parametrize("env_id", ["proprio_env/ElbowReach-v0",
                                    "proprio_env/ProsthesisElbow-v0"])
def test_vector_env_soak_short(env_id):
    """A short soak of the vector env (random and corner actions, autoresets); the long one
    is ``python scripts/soak_env.py --num-envs 64 --steps 1000000``."""
    result = soak_env.soak_vector(env_id, 8 * 230, num_envs=8, seed=2)
    assert result["steps"] == 8 * 230 and result["episodes"] == 8 + 8
    lo, hi = result["extremes"]["angle_deg"]
    assert -5 <= lo and hi <= 135
