"""The env core's two evaluations of one arithmetic: a single env computes its rewards and
``info`` on Python floats, a vector env on (n,) arrays (``proprio_env.envs.core``). Sub-env i
of a vector env is the reference: every number of the env core equal, bit for bit, not to a
tolerance. Also
the C batch chain's kept push buffers: pushes of changing block sizes, non-contiguous and
integer inputs give what fresh arrays gave (the one-arm ``CArmChain`` is the reference)."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import proprio_env  # noqa: F401  (registers the envs)
from proprio_env.envs.core import rewards, scalar_info

IDS = ("proprio_env/ElbowReach-v0", "proprio_env/ProsthesisElbow-v0")


@pytest.mark.parametrize("env_id", IDS)
@pytest.mark.parametrize("backend", ["numpy", "c"])
def test_single_env_info_and_reward_are_the_vector_envs_bit_for_bit(env_id, backend):
    pytest.importorskip("spindle.native.chain")
    n, seed = 3, 5
    kwargs = {"backend": backend, "control_cost_weight": 0.05, "include_fusimotor": True}
    venv = gym.make_vec(env_id, num_envs=n, max_episode_steps=200, **kwargs)
    singles = [gym.make(env_id, max_episode_steps=200, **kwargs) for _ in range(n)]
    venv.reset(seed=seed)
    for i, env in enumerate(singles):
        env.reset(seed=seed + i)
    rng = np.random.default_rng(0)
    space = venv.single_action_space
    for _ in range(6):
        a = rng.uniform(space.low, space.high, (n, *space.shape)).astype(np.float32)
        _, reward, _, _, info = venv.step(a)
        for i, env in enumerate(singles):
            _, r, _, _, i_info = env.step(a[i])
            assert type(r) is float and r == reward[i]
            assert list(i_info) == list(info)
            for key, value in i_info.items():
                if np.ndim(value) == 0:
                    assert type(value) in (float, int), key
                    assert value == info[key][i], key
                else:  # the chain's outputs: the numpy chain over 3 arms and over 1
                    # rounds differently (array lengths), the C chain is exact
                    assert isinstance(value, np.ndarray) and value.flags.writeable, key
                    np.testing.assert_allclose(value, info[key][i], err_msg=key,
                                               rtol=0 if backend == "c" else 1e-12)
    venv.close()


def test_the_arithmetic_is_one_on_floats_and_arrays():
    rng = np.random.default_rng(1)
    cols = rng.normal(size=(5, 50))
    distance, control = rng.normal(size=50), rng.random(50)
    arrays = scalar_info(*cols, distance, control, np.degrees)
    for i in range(50):
        floats = scalar_info(*cols[:, i].tolist(), distance[i], control[i], math.degrees)
        for key, value in floats.items():
            assert value == arrays[key][i], key
    angle, target, square = rng.uniform(0, 130, (3, 50))
    d, c = rewards(angle, target, square, 1.3, 0.05)
    for i in range(50):
        di, ci = rewards(float(angle[i]), float(target[i]), float(square[i]), 1.3, 0.05)
        assert (di, ci) == (d[i], c[i])


@pytest.mark.parametrize("variant", ["double", "float"])
def test_kept_push_buffers_across_block_sizes_and_inputs(variant):
    chain_module = pytest.importorskip("spindle.native.chain")
    n = 3
    batch = chain_module.CArmChainBatch(n, variant=variant)
    singles = [chain_module.CArmChain(variant=variant) for _ in range(n)]
    angles = np.array([30.0, 60.0, 90.0])
    batch.reset(angles, 0.0)
    for k, chain in enumerate(singles):
        chain.reset(float(angles[k]), 0.0)
    t0 = 0.0
    rng = np.random.default_rng(2)
    for k in (10, 3, 10, 1, 7):  # block sizes change: each has its own buffers
        t = t0 + 0.002 * np.arange(1, k + 1)
        t0 = float(t[-1])
        wide = np.empty((n, k, 3))  # a strided view as the times, ints as the angles
        wide[:, :, 1] = t
        angle = (angles[:, None] + rng.integers(-3, 4, (n, k)).cumsum(axis=1)).astype(np.int64)
        counts = np.array([k, max(k - 1, 0), k])
        out = batch.push_angle_block(wide[:, :, 1], angle, n_samples=counts)
        for i, chain in enumerate(singles):
            one = chain.push_angle_block(t[:counts[i]], angle[i, :counts[i]].astype(float))
            assert out.t_s[i] == one.t_s
            np.testing.assert_array_equal(out.ia_pps[i], one.ia_pps)
            np.testing.assert_array_equal(out.ii_pps[i], one.ii_pps)
    with pytest.raises(ValueError, match="n_samples has dtype bool"):
        batch.push_angle_block(t[None].repeat(n, 0), np.ones((n, t.size)),
                               n_samples=np.ones(n, bool))
    with pytest.raises(ValueError, match=r"n_samples\[1\]=-1 must lie"):
        batch.push_angle_block(t[None].repeat(n, 0), np.ones((n, t.size)),
                               n_samples=np.array([0, -1, 0]))
