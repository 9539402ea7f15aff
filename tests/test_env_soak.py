"""Soak (slow): long random-action runs stay finite and bounded; bad actions are rejected.

The full 10^6-step soak is ``python scripts/soak_env.py --steps 1000000``."""

from __future__ import annotations

import pytest

from proprio_env.experiments import soak as soak_env


@pytest.mark.slow
@pytest.mark.parametrize("env_id", ["proprio_env/ElbowReach-v0",
                                    "proprio_env/ProsthesisElbow-v0",
                                    "proprio_env/ElbowReach-v1",
                                    "proprio_env/ProsthesisElbow-v1"])
def test_random_actions_stay_finite_and_bounded(env_id):
    result = soak_env.soak(env_id, 10_000, seed=3)
    assert result["episodes"] == 10_000 // 200 + 1
    assert result["bad_actions_rejected"] == 2 * 10
    lo, hi = result["extremes"]["angle_deg"]
    assert -5 <= lo and hi <= 135
    if env_id.endswith("-v1"):  # Ib checked finite and >= 0 at every step (check_step)
        assert result["extremes"]["ib_pps"][1] > 10.0
        if "ib_numpy_c_max_diff_pps" in result:
            assert result["ib_numpy_c_max_diff_pps"] <= soak_env.IB_TWIN_TOLERANCE_PPS


@pytest.mark.parametrize("env_id", ["proprio_env/ElbowReach-v1",
                                    "proprio_env/ProsthesisElbow-v1"])
def test_ib_soak_short_c_equals_numpy_twin(env_id):
    """600 random steps (3 episodes) of a v1 env with C organs: Ib finite, >= 0 and within
    1e-9 pps of a numpy twin fed the same forces at every step (measured ~1e-13)."""
    result = soak_env.soak(env_id, 600, seed=4, backend="c")
    assert result["ib_numpy_c_max_diff_pps"] <= soak_env.IB_TWIN_TOLERANCE_PPS
    lo, hi = result["extremes"]["ib_pps"]
    assert lo >= 0.0 and hi > 10.0
    assert result["force_rule"] == {"held": 0, "clamped": 0}


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
    with_ib = {**info, "ib_pps": np.array([3.0, 0.0]), "force_N": np.array([10.0, 0.0])}
    soak_env.check_step(np.zeros(7, np.float32), with_ib, (0, 130), 1)
    for key, bad in (("ib_pps", [np.nan, 1.0]), ("ib_pps", [-1e-3, 1.0]),
                     ("force_N", [np.inf, 0.0])):
        with pytest.raises(soak_env.SoakError, match=key):
            soak_env.check_step(np.zeros(7), {**with_ib, key: np.array(bad)}, (0, 130), 1)


@pytest.mark.parametrize("env_id", ["proprio_env/ElbowReach-v0",
                                    "proprio_env/ProsthesisElbow-v0",
                                    "proprio_env/ElbowReach-v1"])
def test_vector_env_soak_short(env_id):
    """A short soak of the vector env (random and corner actions, autoresets); the long one
    is ``python scripts/soak_env.py --num-envs 64 --steps 1000000``."""
    result = soak_env.soak_vector(env_id, 8 * 230, num_envs=8, seed=2)
    assert result["steps"] == 8 * 230 and result["episodes"] == 8 + 8
    lo, hi = result["extremes"]["angle_deg"]
    assert -5 <= lo and hi <= 135
