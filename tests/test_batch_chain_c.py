"""The C batched chain (CArmChainBatch, ps_chain_batch_* in chain.c) against the single C chain.

The reference is a CArmChain per arm (itself tested against the numpy chain in
test_c_chain.py) fed the same samples in the same order: arm k of the batch must give the same
outputs (within 1e-12) and the same counters, on streams full of every fault a handling rule is
for, split into ragged blocks; a push that fails in one arm must leave every arm as it was.
"""

from __future__ import annotations

import copy
import json
import math
import os
import pickle
import shutil
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from spindle.chain import (
    BACKEND_CHOICES,
    BACKENDS,
    COUNTERS,
    ArmSample,
    ChainConfig,
    make_batched_chain,
    resolve_backend,
)
from spindle.native import abi, build

try:
    build.find_compiler()
except build.CBackendError:  # pragma: no cover - CI has a compiler
    pytest.skip("no C compiler: the C backend cannot be built", allow_module_level=True)

from spindle.native.chain import CArmChain, CArmChainBatch

REPO = Path(build.__file__).resolve().parents[2]
C = ChainConfig(backend="c")
TOL = 1e-12
KINDS = ("counts", "angle_deg", "length_L0")
N_ARMS = 5


# -- fault streams ----------------------------------------------------------------------------
def fault_stream(kind: str, seed: int, n: int = 260) -> tuple[np.ndarray, np.ndarray]:
    """(times, values) of one arm: a moving elbow sampled at 500 Hz with every kind of bad
    sample: NaN and out-of-range readings / angles / lengths, repeated, backwards and NaN times,
    gaps, long gaps (restarts) and a burst of 7 earlier times (a clock resync)."""
    rng = np.random.default_rng(seed)
    probe = CArmChain(C)
    cal, max_count = C.calibration, C.encoder.max_count
    times, values = [], []
    t, i = 0.0, 0
    while len(times) < n:
        i += 1
        event = rng.random()
        if event < 0.04:
            t_i = t  # repeated
        elif event < 0.08:
            t_i = t - 0.01  # backwards
        elif event < 0.10:
            t_i = math.nan
        elif event < 0.13:
            t = t_i = t + 0.03  # a gap, bridged
        elif event < 0.15:
            t = t_i = t + 0.2  # a long gap: restart
        elif event < 0.16:  # 7 earlier times: the 7th resyncs the clock
            back = t - 1.0
            for j in range(7):
                times.append(back + 0.002 * j)
                values.append(None)
            t = back + 0.002 * 6
            continue
        else:
            t = t_i = t + 0.002 * rng.uniform(0.8, 1.2)
        times.append(t_i)
        values.append(None)
    angle = 60 + 45 * np.sin(2 * np.pi * 1.3 * np.nan_to_num(np.array(times)) + seed)
    angle += rng.normal(0, 2, angle.shape)
    bad = rng.random(len(times))
    if kind == "counts":
        x = np.round(np.asarray(cal.counts(angle), dtype=float))
        x[bad < 0.03] = math.nan
        x[(bad >= 0.03) & (bad < 0.06)] = -1.0
        x[(bad >= 0.06) & (bad < 0.08)] = max_count + 7.0
        x[(bad >= 0.08) & (bad < 0.09)] = 100.5
        x[(bad >= 0.09) & (bad < 0.11)] = rng.integers(0, max_count + 1, 1)  # spikes
    elif kind == "angle_deg":
        x = angle.copy()
        x[bad < 0.03] = math.nan
        x[(bad >= 0.03) & (bad < 0.05)] = math.inf
        x[(bad >= 0.05) & (bad < 0.08)] = 170.0  # clamped, and a slew-limited jump
    else:
        x = np.array([probe.fits.length_L0(math.radians(a)) for a in np.clip(angle, 1, 129)])
        x[bad < 0.03] = math.nan
        x[(bad >= 0.03) & (bad < 0.05), 0] = 0.3
        x[(bad >= 0.05) & (bad < 0.07), 1] = 1.7
        x[(bad >= 0.07) & (bad < 0.10)] += 0.05  # slew-limited jumps
    return np.array(times), x


def streams(kind: str) -> list[tuple[np.ndarray, np.ndarray]]:
    return [fault_stream(kind, seed) for seed in range(N_ARMS)]


def fresh(angles=(40.0, 55.0, 70.0, 85.0, 100.0)) -> tuple[CArmChainBatch, list[CArmChain]]:
    batch = make_batched_chain(len(angles), C)
    batch.reset(np.array(angles))
    singles = [CArmChain(C) for _ in angles]
    for chain, angle in zip(singles, angles, strict=True):
        chain.reset(angle)
    return batch, singles


def assert_arm(batch_out, k: int, single: ArmSample, where: str) -> None:
    arm = batch_out.arm(k)
    assert arm.accepted == single.accepted, where
    for f in fields(ArmSample):
        a = np.asarray(getattr(single, f.name), dtype=float)
        b = np.asarray(getattr(arm, f.name), dtype=float)
        assert a.shape == b.shape, (where, f.name)
        assert np.allclose(a, b, rtol=0, atol=TOL, equal_nan=True), (where, f.name, a, b)


def assert_counters(batch: CArmChainBatch, singles: list[CArmChain], where: str) -> None:
    counted = batch.counters
    assert set(counted) == set(COUNTERS)
    for k, chain in enumerate(singles):
        assert {name: int(counted[name][k]) for name in COUNTERS} == chain.counters, (where, k)


def block_push(kind: str):
    return {"counts": "push_counts_block", "angle_deg": "push_angle_block",
            "length_L0": "push_lengths_block"}[kind]


def one_push(kind: str):
    return {"counts": "push_counts", "angle_deg": "push_angle",
            "length_L0": "push_lengths"}[kind]


# -- equivalence ------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
def test_ragged_blocks_equal_each_arms_single_chain(kind):
    data = streams(kind)
    batch, singles = fresh()
    rng = np.random.default_rng(7)
    k = 10
    at = [0] * N_ARMS
    calls = 0
    while any(a < len(t) for a, (t, _) in zip(at, data, strict=True)):
        n_samples = np.array([min(int(rng.integers(0, k + 1)), len(t) - a)
                              for a, (t, _) in zip(at, data, strict=True)])
        shape = (N_ARMS, k, 2) if kind == "length_L0" else (N_ARMS, k)
        t_block = np.full((N_ARMS, k), math.nan)  # padding: never read
        x_block = np.full(shape, math.nan)
        for i, (t, x) in enumerate(data):
            t_block[i, :n_samples[i]] = t[at[i]:at[i] + n_samples[i]]
            x_block[i, :n_samples[i]] = x[at[i]:at[i] + n_samples[i]]
        out = getattr(batch, block_push(kind))(t_block, x_block, n_samples=n_samples)
        for i, chain in enumerate(singles):
            single = getattr(chain, block_push(kind))(t_block[i, :n_samples[i]],
                                                      x_block[i, :n_samples[i]])
            if n_samples[i] == 0:  # no sample: its last output, not accepted
                single = ArmSample(**{**single.__dict__, "accepted": False})
            assert_arm(out, i, single, f"call {calls} arm {i}")
            at[i] += int(n_samples[i])
        assert_counters(batch, singles, f"call {calls}")
        calls += 1
    # every rule fired somewhere, so the comparison covered it
    totals = {name: int(v.sum()) for name, v in batch.counters.items()}
    expected = {"restarts", "clock_resyncs", "gaps", "time_backwards", "repeated_time",
                "bad_time", "slew_limited",
                {"counts": "invalid_reading", "angle_deg": "invalid_angle",
                 "length_L0": "invalid_length"}[kind]}
    assert all(totals[name] > 0 for name in expected), totals
    state, reference = batch.spindle_state, [c.spindle_state for c in singles]
    for name in ("tension_FU", "polar_velocity_L0_s", "activation", "length_L0"):
        want = np.concatenate([getattr(s, name) for s in reference])
        np.testing.assert_allclose(getattr(state, name), want, rtol=0, atol=TOL)


@pytest.mark.parametrize("kind", KINDS)
def test_one_sample_per_arm_with_an_active_mask(kind):
    data = streams(kind)
    batch, singles = fresh()
    rng = np.random.default_rng(3)
    at = [0] * N_ARMS
    for step in range(200):
        active = rng.random(N_ARMS) < 0.8
        t = np.array([d[0][min(a, len(d[0]) - 1)] for a, d in zip(at, data, strict=True)])
        x = np.array([d[1][min(a, len(d[1]) - 1)] for a, d in zip(at, data, strict=True)])
        before = [bytes(batch._chains[i]) for i in range(N_ARMS)]
        out = getattr(batch, one_push(kind))(t, x, active=active)
        for i, chain in enumerate(singles):
            if active[i]:
                single = getattr(chain, one_push(kind))(t[i], x[i])
                at[i] += 1
            else:  # untouched, its last output repeated as not accepted
                assert bytes(batch._chains[i]) == before[i], (step, i)
                single = ArmSample(**{**chain.last.__dict__, "accepted": False})
            assert_arm(out, i, single, f"step {step} arm {i}")
        assert_counters(batch, singles, f"step {step}")
    everyone = getattr(batch, one_push(kind))(t, x)  # active=None: every arm
    for i, chain in enumerate(singles):
        assert_arm(everyone, i, getattr(chain, one_push(kind))(t[i], x[i]), f"all, arm {i}")


def test_reset_of_some_arms_and_the_switch():
    batch, singles = fresh()
    t = np.tile(0.002 * np.arange(1, 11), (N_ARMS, 1))
    batch.push_angle_block(t, np.full((N_ARMS, 10), 50.0))
    for i, chain in enumerate(singles):
        chain.push_angle_block(t[i], np.full(10, 50.0))
    untouched = [bytes(batch._chains[i]) for i in (0, 2, 4)]
    out = batch.reset(np.array([30.0, 140.0]), t_s=np.array([5.0, 6.0]), arms=np.array([3, 1]))
    singles[3].reset(30.0, 5.0)
    singles[1].reset(140.0, 6.0)
    assert [bytes(batch._chains[i]) for i in (0, 2, 4)] == untouched
    for i, chain in enumerate(singles):
        assert_arm(out, i, chain.last, f"arm {i}")
    assert_counters(batch, singles, "after reset")
    assert batch.counters["angle_clamped"][1] == 1 and batch.counters["accepted"][1] == 0
    lengths = np.array([[1.0, 1.1], [0.95, 1.2]])
    batch.reset(np.array([20.0, 90.0]), 7.0, length_L0=lengths, arms=np.array([0, 4]))
    singles[0].reset(20.0, 7.0, length_L0=lengths[0])
    singles[4].reset(90.0, 7.0, length_L0=lengths[1])
    # the switch: arms 1 and 3 follow an intended angle, the others their measured motion
    intended = np.array([math.nan, 100.0, math.nan, 10.0, math.nan])
    batch.set_intended_angle(intended)
    for i, chain in enumerate(singles):
        chain.set_intended_angle(None if math.isnan(intended[i]) else intended[i])
    starts = np.array([c.last.t_s for c in singles])
    t = starts[:, None] + 0.002 * np.arange(1, 21)
    angles = np.linspace(40, 80, 20)
    out = batch.push_angle_block(t, np.tile(angles, (N_ARMS, 1)))
    for i, chain in enumerate(singles):
        assert_arm(out, i, chain.push_angle_block(t[i], angles), f"switch arm {i}")
    batch.set_intended_angle(None)
    for chain in singles:
        chain.set_intended_angle(None)
    out = batch.push_angle(t[:, -1] + 0.002, np.full(N_ARMS, 60.0))
    for i, chain in enumerate(singles):
        assert_arm(out, i, chain.push_angle(t[i, -1] + 0.002, 60.0), f"measured arm {i}")
    with pytest.raises(ValueError, match="arm 2"):
        batch.set_intended_angle(np.array([1.0, 2.0, math.inf, 4.0, 5.0]))


def test_a_failing_arm_leaves_every_arm_as_it_was():
    batch, _ = fresh()
    t = np.tile(0.002 * np.arange(1, 6), (N_ARMS, 1))
    batch.push_angle_block(t, np.full((N_ARMS, 5), 50.0))
    before = bytes(batch._chains)
    last, counters = batch.last, batch.counters
    params = batch._chains[N_ARMS - 1].config.params  # the last arm: all others went first
    saved = params.M[0]
    params.M[0] = math.nan  # an injected fault: that arm's next spindle step fails
    faulty = bytes(batch._chains)
    for push, args in (
            ("push_angle_block", (t + 0.01, np.full((N_ARMS, 5), 60.0))),
            ("push_counts_block", (t + 0.01, np.full((N_ARMS, 5), 400.0))),
            ("push_lengths_block", (t + 0.01, np.full((N_ARMS, 5, 2), 1.0))),
            ("push_angle", (t[:, 0] + 0.01, np.full(N_ARMS, 60.0))),
            ("push_counts", (t[:, 0] + 0.01, np.full(N_ARMS, 400.0))),
            ("push_lengths", (t[:, 0] + 0.01, np.full((N_ARMS, 2), 1.0)))):
        with pytest.raises(FloatingPointError, match=f"arm {N_ARMS - 1} .*no arm changed"):
            getattr(batch, push)(*args)
        assert bytes(batch._chains) == faulty, push
    params.M[0] = saved
    assert bytes(batch._chains) == before
    assert all(np.array_equal(v, counters[k]) for k, v in batch.counters.items())
    assert np.array_equal(batch.last.ia_pps, last.ia_pps)
    out = batch.push_angle_block(t + 0.01, np.full((N_ARMS, 5), 60.0))  # and it carries on
    assert out.accepted.all() and (batch.counters["accepted"] == 10).all()


def test_pickle_and_deepcopy_continue_bit_identically():
    t_all, x_all = fault_stream("counts", 11, 120)
    batch, _ = fresh()

    def feed(chain, rows):
        outs = []
        for r in rows:
            outs.append(chain.push_counts_block(np.tile(t_all[r * 10:(r + 1) * 10], (N_ARMS, 1)),
                                                np.tile(x_all[r * 10:(r + 1) * 10], (N_ARMS, 1))))
        return outs

    feed(batch, range(6))
    copies = [pickle.loads(pickle.dumps(batch)), copy.deepcopy(batch)]
    assert all(type(c) is CArmChainBatch and c.n_arms == N_ARMS for c in copies)
    reference = feed(batch, range(6, 12))
    for c in copies:
        for a, b in zip(feed(c, range(6, 12)), reference, strict=True):
            for f in fields(ArmSample):
                assert np.array_equal(getattr(a, f.name), getattr(b, f.name), equal_nan=True)
        assert bytes(c._chains) == bytes(batch._chains)


def test_shapes_and_arguments_are_checked():
    batch, _ = fresh()
    t = np.tile(0.002 * np.arange(1, 4), (N_ARMS, 1))
    with pytest.raises(ValueError, match=r"length_L0 has shape \(5, 3\), expected \(5, 3, 2\)"):
        batch.push_lengths_block(t, np.ones((N_ARMS, 3)))
    with pytest.raises(ValueError, match=r"t_s has shape \(4,\), expected \(5,\)"):
        batch.push_angle(np.zeros(4), np.zeros(N_ARMS))
    with pytest.raises(ValueError, match=r"n_samples\[2\]=4 must lie in 0..3"):
        batch.push_angle_block(t, np.ones((N_ARMS, 3)), n_samples=np.array([1, 2, 4, 0, 0]))
    with pytest.raises(ValueError, match="active has dtype"):
        batch.push_angle(t[:, 0], np.ones(N_ARMS), active=np.ones(N_ARMS))
    with pytest.raises(ValueError, match="arm 3 must be a finite"):
        batch.reset(np.array([1.0, 2.0, 3.0, math.nan, 5.0]))
    with pytest.raises(ValueError, match="of arm 4 must be 2 finite lengths"):
        batch.reset(np.array([1.0, 2.0]), length_L0=np.array([[1, 1], [1, 2.0]]),
                    arms=np.array([0, 4]))
    with pytest.raises(ValueError, match=r"outside 0\.\.4"):
        batch.reset(np.array([1.0]), arms=np.array([5]))
    with pytest.raises(ValueError, match="repeats"):
        batch.reset(np.array([1.0, 2.0]), arms=np.array([1, 1]))
    with pytest.raises(ValueError, match="n_arms"):
        CArmChainBatch(0, C)
    never = CArmChainBatch(2, C)
    with pytest.raises(RuntimeError, match="reset"):
        never.push_angle(np.array([0.1, 0.1]), np.array([1.0, 1.0]))
    with pytest.raises(RuntimeError, match="reset"):
        never.last  # noqa: B018 - the property raises
    with pytest.raises(RuntimeError, match="arm 0 was never reset"):
        never.reset(np.array([30.0]), arms=np.array([1]))
    assert (never._table["stage"] < 2).all()
    # the C entry point itself refuses n_samples outside 0..k, before touching any arm
    before = bytes(batch._chains)
    failed = (abi.ctypes.c_long(), abi.ctypes.c_long())
    c_long = np.dtype(f"i{abi.ctypes.sizeof(abi.ctypes.c_long)}")
    n_samples = np.array([0, 0, 5, 0, 0], dtype=c_long)
    status = batch._lib.ps_chain_batch_push_angle_block(
        abi.ctypes.addressof(batch._chains), N_ARMS, 3, n_samples.ctypes.data,
        np.ascontiguousarray(t).ctypes.data, np.ones((N_ARMS, 3)).ctypes.data,
        abi.ctypes.addressof(batch._work), None, *map(abi.ctypes.pointer, failed))
    assert status == abi.Status.PS_ERR_ARGUMENT and failed[0].value == 2
    assert bytes(batch._chains) == before


# -- backend="auto" ---------------------------------------------------------------------------
AUTO_CHILD = """
import json, os, sys
from spindle.chain import ChainConfig, make_chain, resolve_backend
out = {}
for name, cc, cache in json.loads(sys.argv[1]):
    os.environ["CC"], os.environ["PROPRIO_C_CACHE"] = cc, cache
    out[name] = [resolve_backend("auto"),
                 make_chain(ChainConfig(backend="auto")).config.backend,
                 type(make_chain(ChainConfig(backend="auto"))).__name__]
print(json.dumps(out))
"""


def test_auto_backend_uses_c_when_it_can_and_falls_back_to_numpy(tmp_path):
    assert resolve_backend("numpy") == "numpy" and resolve_backend("c") == "c"
    assert BACKENDS == ("numpy", "c") and BACKEND_CHOICES == ("numpy", "c", "auto")
    assert ChainConfig(backend="auto").backend == "auto"  # resolved when a chain is built
    with pytest.raises(ValueError, match="fortran"):
        resolve_backend("fortran")
    # this module runs only where a compiler is (see its top), so "auto" must mean C here
    assert make_batched_chain(2, ChainConfig(backend="auto")).config.backend == "c"
    # a valid cached library, copied from this run's cache (made by the tests above)
    library = build.library_path("double")
    valid = tmp_path / "valid"
    valid.mkdir()
    shutil.copy2(library, valid / library.name)
    for manifest in library.parent.glob("*.json"):
        if library.name.startswith(manifest.stem):
            shutil.copy2(manifest, valid / manifest.name)
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty2").mkdir()
    cases = [("no compiler, empty cache", str(tmp_path / "no-such-cc"), str(tmp_path / "empty")),
             ("failing compiler", shutil.which("false") or "false", str(tmp_path / "empty2")),
             ("no compiler, valid cache", str(tmp_path / "no-such-cc"), str(valid))]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO),
                                                         os.environ.get("PYTHONPATH", "")])}
    result = subprocess.run([sys.executable, "-c", AUTO_CHILD, json.dumps(cases)], env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    got = json.loads(result.stdout)
    assert got["no compiler, empty cache"] == ["numpy", "numpy", "ArmChain"]
    assert got["failing compiler"] == ["numpy", "numpy", "ArmChain"]
    assert got["no compiler, valid cache"] == ["c", "c", "CArmChain"]
    assert not list((tmp_path / "empty2").glob("*.so"))  # nothing half-built was kept
