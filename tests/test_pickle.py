"""Pickling and deep copies of the envs and the chains, both backends: a copy taken at any
point continues bit-identically to the original (observations, rewards, infos, outputs,
counters), and copies are independent of it."""

from __future__ import annotations

import copy
import pickle

import gymnasium as gym
import numpy as np
import pytest

import proprio_env
from proprio_env.envs.afferents import SOURCES
from spindle.chain import BACKENDS, ArmSample, ChainConfig, make_chain

IDS = tuple(proprio_env.ENV_IDS)


def _same(a, b) -> bool:
    """Bit-for-bit equality of env outputs (arrays by bytes, floats by bits, dicts by key)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, ArmSample):
        return _same(vars(a), vars(b))
    if isinstance(a, np.ndarray | float | np.floating):
        a, b = np.asarray(a), np.asarray(b)
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    return type(a) is type(b) and a == b


def _clones(obj):
    return {"pickle": pickle.loads(pickle.dumps(obj)), "deepcopy": copy.deepcopy(obj)}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("env_id", IDS)
def test_env_copy_continues_bit_identically(env_id, source, backend):
    env = gym.make(env_id, backend=backend, afferent_source=source)
    env.action_space.seed(5)
    actions = [env.action_space.sample() for _ in range(16)]
    env.reset(seed=9)
    for a in actions[:8]:  # mid-episode, the arm moving
        env.step(a)
    clones = _clones(env)
    moved = 0.0
    for a in actions[8:]:
        ref = env.step(a)
        moved = max(moved, abs(ref[4]["angular_velocity_deg_s"]))
        for how, clone in clones.items():
            out = clone.step(a)
            assert _same(out, ref), f"{how} copy diverged"
    assert moved > 1.0  # the copies were taken and compared during a movement
    # A copy is independent: stepping it did not move the original (and the reverse).
    assert clones["pickle"].unwrapped.data is not env.unwrapped.data
    chain, copied = env.unwrapped.afferents.chain, clones["deepcopy"].unwrapped.afferents.chain
    assert chain.counters == copied.counters and chain.counters["accepted"] > 0
    env.close()


def _movement(n: int, t0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    t = t0 + 0.002 * np.arange(1, n + 1)
    return t, 70.0 + 40.0 * np.sin(2 * np.pi * 1.5 * t)


@pytest.mark.parametrize("variant", ["double", "float"])
def test_c_chain_copied_mid_movement_continues_bit_identically(variant):
    from spindle.native.chain import CArmChain

    chain = CArmChain(ChainConfig(backend="c"), variant=variant)
    chain.reset(70.0, 0.0)
    t, angle = _movement(150)
    chain.push_angle_block(t[:100], angle[:100])
    # Handling rules hit before the copy, so counters and the median state are not trivial.
    chain.push_angle(t[99], angle[99])            # repeated time
    chain.push_angle(t[100], float("nan"))        # invalid angle
    chain.push_counts(t[100], 300)                # an encoder reading: median filter state
    chain.set_intended_angle(90.0)
    chain.push_angle(t[101], angle[101])
    for clone in _clones(chain).values():
        assert type(clone) is CArmChain and clone.variant == variant
        assert clone.counters == chain.counters
        assert _same(clone.last, chain.last)
        assert _same(vars(clone.spindle_state), vars(chain.spindle_state))
    clones = _clones(chain)
    for i in range(102, 150):
        if i == 120:
            for c in (chain, *clones.values()):
                c.set_intended_angle(None)
        ref = chain.push_angle(t[i], angle[i]) if i % 3 else chain.push_counts(t[i], 200 + i)
        for how, clone in clones.items():
            out = clone.push_angle(t[i], angle[i]) if i % 3 else clone.push_counts(t[i], 200 + i)
            assert _same(out, ref), f"{how} copy diverged at sample {i}"
            assert clone.counters == chain.counters
    t2, angle2 = _movement(40, t[-1])
    ref = chain.push_angle_block(t2, angle2)
    for clone in clones.values():
        assert _same(clone.push_angle_block(t2, angle2), ref)
    assert chain.counters["accepted"] == 100 + 2 + 48 + 40


def test_c_chain_copies_are_independent_and_agree_with_numpy():
    chains = {b: make_chain(ChainConfig(backend=b)) for b in BACKENDS}
    t, angle = _movement(120)
    for c in chains.values():
        c.reset(70.0, 0.0)
        c.push_angle_block(t[:60], angle[:60])
    copies = {b: copy.deepcopy(c) for b, c in chains.items()}
    for c in copies.values():  # drive the copies elsewhere: the originals must not notice
        c.push_angle_block(t[60:], np.full(60, 20.0))
    out = {b: c.push_angle_block(t[60:], angle[60:]) for b, c in chains.items()}
    np.testing.assert_allclose(out["c"].ia_pps, out["numpy"].ia_pps, rtol=0, atol=1e-9)
    assert chains["c"].counters == chains["numpy"].counters
    assert copies["c"].counters == copies["numpy"].counters
    assert copies["c"].last.angle_deg == 20.0 != out["c"].angle_deg


def test_c_chain_pickled_before_reset_still_needs_reset():
    chain = make_chain(ChainConfig(backend="c"))
    clone = pickle.loads(pickle.dumps(chain))
    with pytest.raises(RuntimeError, match="reset"):
        clone.push_angle(0.002, 70.0)
    assert _same(clone.reset(70.0, 0.0), chain.reset(70.0, 0.0))
