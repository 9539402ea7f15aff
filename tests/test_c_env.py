"""The envs on the C chain backend give the numpy backend's afferents (same physics, same
chain; the double C build agrees with numpy to round-off)."""

import gymnasium as gym
import numpy as np
import pytest

import proprio_env  # noqa: F401  (registers the ids)


@pytest.mark.parametrize("env_id", ["proprio_env/ElbowReach-v0", "proprio_env/ProsthesisElbow-v0"])
def test_c_backend_env_equals_numpy_backend(env_id):
    traces = {}
    for backend in ("numpy", "c"):
        env = gym.make(env_id, backend=backend)
        env.reset(seed=3)
        rng = np.random.default_rng(0)
        rows = []
        for _ in range(60):
            action = rng.uniform(env.action_space.low, env.action_space.high)
            _, _, _, _, info = env.step(action.astype(np.float32))
            rows.append(np.concatenate([info["ia_pps"], info["ii_pps"],
                                        info["gamma_static_pps"], info["gamma_dynamic_pps"]]))
        env.close()
        traces[backend] = np.array(rows)
    assert traces["numpy"][:, :4].max() > 1.0  # the spindles fire
    # measured 8.3e-13 pps (II, ProsthesisElbow-v0), 2.1e-13 pps (Ia); the drives bit for bit
    # or within 4.3e-14 pps (2026-12-02)
    np.testing.assert_allclose(traces["c"], traces["numpy"], rtol=0, atol=3e-12)
