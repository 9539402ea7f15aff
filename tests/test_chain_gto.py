"""The force sense in the chain: load word -> torque -> BRA/TRImed tendon forces -> Ib.

Checked against independent references (the continuous tendon organ solved by scipy at tight
tolerance, the closed-form rest rate, the moment-arm split done by hand), against the rules of
docs/faults.md (each load rule against the chain fed what the rule says it stands for), and
across implementations: numpy = C, arm k of a batch = a single chain, numpy single = batched.
"""

import math
from dataclasses import fields, replace

import numpy as np
import pytest

from proprio_env.body.encoder import Encoder, LoadSensor
from spindle.chain import (
    ArmChain,
    ArmSample,
    ChainConfig,
    make_batched_chain,
    make_chain,
    run_chain,
)
from spindle.chain.batch import ArmChainBatch
from spindle.chain.force import load_moment_arm_fits
from spindle.chain.sensor import AX12, AX12_LOAD, LOAD_DIRECTION_BIT, LoadParams, load_torque_Nm
from spindle.native import abi, build
from spindle.tendon_organ_params import HUMAN as GTO_HUMAN
from spindle.tendon_organ_params import static_rate_pps
from spindle.tendon_organ_reference import reference_rates

try:
    build.find_compiler()
    HAVE_C = True
except build.CBackendError:  # pragma: no cover - CI has a compiler
    HAVE_C = False
needs_c = pytest.mark.skipif(not HAVE_C, reason="no C compiler")

NUMPY = ChainConfig(backend="numpy")
C = ChainConfig(backend="c")


def word(torque_Nm: float) -> float:
    """The exact load word of a torque (no noise), by the AX-12's format written out here."""
    counts = round(abs(torque_Nm) / (1.5 / 1023))
    return float(min(counts, 1023) + (LOAD_DIRECTION_BIT if torque_Nm < 0 else 0))


def faulty_trace(duration_s=2.0, seed=0, load_invalid=0.03):
    """A 0.7 Hz elbow swing through the noisy encoder and a noisy load sensor (1.1 Hz torque
    of 0.8 N m) with invalid words, plus hand-placed faults of every kind."""
    t = np.arange(0.0, duration_s, 2e-3)
    angle = 65 + 40 * np.sin(2 * np.pi * 0.7 * t)
    t_s, counts = Encoder(replace(AX12, invalid_rate=0.01), rng=seed).record(t, angle)
    torque = 0.8 * np.sin(2 * np.pi * 1.1 * t_s)
    load = LoadSensor(replace(AX12_LOAD, invalid_rate=load_invalid), rng=seed + 1).read_block(
        torque)
    load[50], load[51], load[52], load[53] = math.nan, 2048.0, 3.5, -1.0
    counts[60] = -1.0  # a rejected sample: its (valid) load word must change nothing
    t_s[300:340] = t_s[300:340] + 0.2  # a 0.2 s jump: a restart at rest at that force
    t_s[340:] += 0.2
    return t_s, counts, load


# -- the stage against independent references --------------------------------------------------
def test_constant_load_rests_at_the_closed_form_rate():
    """Reset at a load and held there: Ib stays at G1 ln(F/G2 + 1), F = tau / r(angle) with r
    read from the moment-arm table by hand (the flexion torque on BRA, the extension torque on
    TRImed, the other muscle at 0), within 1e-9 pps over 1 s of samples."""
    fits = load_moment_arm_fits()
    chain = ArmChain(NUMPY)
    counts = float(np.round(chain.config.calibration.counts(50.0)))
    angle = float(chain.config.calibration.angle_deg(counts))
    t = np.arange(1, 501) * 2e-3
    for w, muscle in ((word(0.6), 0), (word(-0.45), 1)):
        chain.reset(angle, 0.0, load=w)
        out = chain.push_counts_block(t, np.full(t.size, counts), load=np.full(t.size, w))
        tau = float(load_torque_Nm(w))
        grid = np.linspace(*fits.valid_range_rad, len(fits.table_m[muscle]))
        r = abs(np.interp(math.radians(angle), grid, fits.table_m[muscle]))
        force = tau / r if muscle == 0 else -tau / r
        assert out.force_N[muscle] == pytest.approx(force, rel=1e-12)
        assert out.force_N[1 - muscle] == 0.0 and out.ib_pps[1 - muscle] == 0.0
        expected = static_rate_pps(GTO_HUMAN, force, chain.config.force_scale_N[muscle])
        assert abs(out.ib_pps[muscle] - expected) < 1e-9  # measured 1e-14
        assert expected > 5.0


def test_load_ramp_follows_the_scipy_reference():
    """A load ramp and hold at a fixed angle: Ib within 1e-7 pps RMS of the continuous model
    solved by Radau at rtol 1e-11, driven by the same force, a line between the samples
    (measured 2.7e-9 pps: the chain steps once per 2 ms sample, exactly for that line up to
    the log's curvature, O(h^4))."""
    chain = ArmChain(NUMPY)
    counts = 512.0
    chain.reset(float(chain.config.calibration.angle_deg(counts)), 0.0, load=0.0)
    t = np.arange(1, 1501) * 2e-3
    torque = np.minimum(t / 0.5, 1.0) * 1.2  # 0 -> 1.2 N m over 0.5 s, then held
    words = np.array([word(x) for x in torque])
    out = [chain.push_counts(ti, counts, wi) for ti, wi in zip(t, words, strict=True)]
    force = np.array([o.force_N[0] for o in out])
    ib = np.array([o.ib_pps[0] for o in out])
    times = np.concatenate(([0.0], t))
    forces = np.concatenate(([0.0], force))
    ref = reference_rates(lambda s: float(np.interp(s, times, forces)), times,
                          chain.config.force_scale_N[0], GTO_HUMAN)[1:]
    assert np.sqrt(np.mean((ib - ref) ** 2)) < 1e-7
    assert ib.max() > 10.0  # the organ really moved


# -- the load rules -----------------------------------------------------------------------------
def test_invalid_words_hold_the_last_torque_and_missing_ones_are_zero():
    """An invalid word's sample equals the sample fed the last valid word (the hold rule); a
    push without load equals one with the zero-torque word 0; both counted."""
    t = np.arange(1, 201) * 2e-3
    counts = 500.0 + (np.arange(200) % 5)
    words = np.array([word(0.5 * math.sin(7 * x)) for x in t])
    faulty = words.copy()
    bad = [10, 11, 40, 120, 121, 122]
    faulty[bad] = [-1.0, math.nan, 5000.0, 0.5, 2048.0, -3.0]
    held = words.copy()
    for i in bad:
        held[i] = held[i - 1]
    a, b = ArmChain(NUMPY), ArmChain(NUMPY)
    for chain in (a, b):
        chain.reset(60.0, 0.0, load=words[0])
    for i in range(200):
        x, y = a.push_counts(t[i], counts[i], faulty[i]), b.push_counts(t[i], counts[i], held[i])
        assert all(np.array_equal(getattr(x, f.name), getattr(y, f.name))
                   for f in fields(ArmSample))
    assert a.counters["invalid_load"] == len(bad) and b.counters["invalid_load"] == 0
    c, d = ArmChain(NUMPY), ArmChain(NUMPY)
    c.reset(60.0, 0.0)
    d.reset(60.0, 0.0, load=0.0)
    c.push_counts_block(t, counts)
    d.push_counts_block(t, counts, load=np.zeros(200))
    assert np.array_equal(c.last.ib_pps, d.last.ib_pps) and c.last.torque_Nm == 0.0
    assert c.counters["missing_load"] == 200 and d.counters["missing_load"] == 0


def test_a_rejected_sample_ignores_its_load_and_a_restart_rests_at_the_new_force():
    chain, clean = ArmChain(NUMPY), ArmChain(NUMPY)
    for ch in (chain, clean):
        ch.reset(60.0, 0.0, load=word(0.2))
    out = chain.push_counts(2e-3, -1.0, word(1.0))  # invalid reading: rejected
    assert not out.accepted and out.torque_Nm == clean.last.torque_Nm
    assert chain.push_counts(0.0, 500.0, word(1.0)).accepted is False  # repeated time
    assert all(np.array_equal(getattr(chain.last, f.name), getattr(clean.last, f.name))
               for f in fields(ArmSample))
    after = chain.push_counts(0.3, 500.0, word(-0.9))  # 0.3 s > max_bridge_s: a restart
    assert chain.counters["restarts"] == 1
    expected = static_rate_pps(GTO_HUMAN, after.force_N[1], chain.config.force_scale_N[1])
    assert after.ib_pps[1] == pytest.approx(expected, rel=1e-12) and after.ib_pps[0] == 0.0


def test_a_reset_with_an_invalid_word_starts_at_zero_torque_counted():
    chain = ArmChain(NUMPY)
    out = chain.reset(60.0, 0.0, load=-1)
    assert out.torque_Nm == 0.0 and np.all(out.ib_pps == 0.0)
    assert chain.counters["invalid_load"] == 1


@pytest.mark.parametrize("backend", ["numpy", pytest.param("c", marks=needs_c)])
def test_a_push_that_raises_leaves_the_chain_as_it_was(backend):
    """A load that stands for an impossible tendon force (a 1e4 N m servo: 8e5 N, above
    MAX_FORCE_N) raises, and the chain, its counters included, is unchanged."""
    chain = make_chain(replace(NUMPY, load=LoadParams(max_torque_Nm=1e4), backend=backend))
    chain.reset(60.0, 0.0, load=1.0)
    chain.push_counts(2e-3, 500.0, 2.0)
    before, counters = chain.last, chain.counters
    with pytest.raises(ValueError, match="MAX_FORCE_N"):
        chain.push_counts(4e-3, 500.0, 1023.0)
    assert chain.counters == counters
    assert all(np.array_equal(getattr(chain.last, f.name), getattr(before, f.name))
               for f in fields(ArmSample))
    after = chain.push_counts(4e-3, 500.0, 2.0)  # the same sample as if the bad one never came
    again = make_chain(replace(NUMPY, load=LoadParams(max_torque_Nm=1e4), backend=backend))
    again.reset(60.0, 0.0, load=1.0)
    again.push_counts(2e-3, 500.0, 2.0)
    assert np.array_equal(again.push_counts(4e-3, 500.0, 2.0).ib_pps, after.ib_pps)


def test_load_arguments_are_checked():
    chain = ArmChain(NUMPY)
    chain.reset(60.0)
    with pytest.raises(ValueError, match="load has shape"):
        chain.push_counts_block([1e-3, 2e-3], [500.0, 500.0], load=[1.0])
    with pytest.raises(ValueError, match="with encoder counts"):
        run_chain(np.arange(3) * 1e-3, angle_deg=np.full(3, 50.0), load=np.zeros(3))
    with pytest.raises(ValueError, match=r"max_bridge_s=0\.2 must be <= 0\.1"):
        ChainConfig(max_bridge_s=0.2)
    with pytest.raises(ValueError, match="max_isometric_force_N"):
        ChainConfig(max_isometric_force_N=(900.0, -1.0))


# -- implementations agree -----------------------------------------------------------------------
@needs_c
def test_numpy_equals_c_with_load_faults():
    """run_chain numpy vs C on a trace with every load fault: Ib within 1e-12 pps (measured
    1.1e-14), forces and torques equal, counters equal."""
    t_s, counts, load = faulty_trace()
    a = run_chain(t_s, counts=counts, load=load, config=NUMPY)
    b = run_chain(t_s, counts=counts, load=load, config=C)
    assert a.counters == b.counters
    assert a.counters["invalid_load"] > 20 and a.counters["restarts"] == 1
    assert np.max(np.abs(a.ib_pps - b.ib_pps)) < 1e-12
    assert np.max(np.abs(a.force_N - b.force_N)) < 1e-12
    np.testing.assert_array_equal(a.torque_Nm, b.torque_Nm)
    assert a.ib_pps.min() >= 0.0 and a.ib_pps.max(axis=0).min() > 5.0


@needs_c
def test_c_blocks_and_resets_with_loads_equal_numpy():
    t_s, counts, load = faulty_trace(1.0, seed=4)
    chains = [ArmChain(NUMPY), make_chain(C)]
    for ch in chains:
        ch.reset(60.0, t_s[0], load=load[0])
    for start in range(1, t_s.size, 13):
        sl = slice(start, start + 13)
        outs = [ch.push_counts_block(t_s[sl], counts[sl], load=load[sl]) for ch in chains]
        assert np.max(np.abs(outs[0].ib_pps - outs[1].ib_pps)) < 1e-12
    assert chains[0].counters == chains[1].counters
    a, b = (ch.tendon_organ_state for ch in chains)
    np.testing.assert_allclose(a.z, b.z, rtol=0, atol=1e-10)
    np.testing.assert_array_equal(a.force_N, b.force_N)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("c", marks=needs_c)])
def test_arm_k_of_a_batch_equals_a_single_chain(backend):
    """Three arms with their own traces and faults, pushed as blocks of 7 and one by one
    (with inactive arms): each equals its single chain (Ib to 1e-12, counters exactly)."""
    config = replace(NUMPY, backend=backend)
    traces = [faulty_trace(0.8, seed=s) for s in (1, 2, 3)]
    k = min(tr[0].size for tr in traces)
    t = np.stack([tr[0][:k] for tr in traces])
    x = np.stack([tr[1][:k] for tr in traces])
    w = np.stack([tr[2][:k] for tr in traces])
    batch = make_batched_chain(3, config)
    singles = [make_chain(config) for _ in range(3)]
    batch.reset(np.full(3, 60.0), t[:, 0], load=w[:, 0])
    for i, ch in enumerate(singles):
        ch.reset(60.0, t[i, 0], load=w[i, 0])
    half = k // 2
    for start in range(1, half, 7):
        sl = slice(start, min(start + 7, half))
        batch.push_counts_block(t[:, sl], x[:, sl], load=w[:, sl])
        for i, ch in enumerate(singles):
            ch.push_counts_block(t[i, sl], x[i, sl], load=w[i, sl])
    for j in range(half, k):
        active = np.array([True, j % 3 != 0, True])
        out = batch.push_counts(t[:, j], x[:, j], active=active, load=w[:, j])
        for i, ch in enumerate(singles):
            if active[i]:
                ch.push_counts(t[i, j], x[i, j], w[i, j])
    for i, ch in enumerate(singles):
        assert np.max(np.abs(out.ib_pps[i] - ch.last.ib_pps)) < 1e-12
        assert out.torque_Nm[i] == ch.last.torque_Nm
        assert {n: int(v[i]) for n, v in batch.counters.items()} == ch.counters


def test_numpy_single_equals_batched_bit_for_bit():
    t_s, counts, load = faulty_trace(0.6, seed=7)
    single, batch = ArmChain(NUMPY), ArmChainBatch(1, NUMPY)
    single.reset(60.0, t_s[0], load=load[0])
    batch.reset(np.array([60.0]), t_s[0], load=load[:1])
    for i in range(1, t_s.size):
        a = single.push_counts(t_s[i], counts[i], load[i])
        b = batch.push_counts(t_s[i:i + 1], counts[i:i + 1], load=load[i:i + 1]).arm(0)
        assert np.array_equal(a.ib_pps, b.ib_pps) and a.torque_Nm == b.torque_Nm


@needs_c
def test_header_constants_of_the_force_sense():
    from spindle.chain.force import MIN_MOMENT_ARM_M
    from spindle.chain.sensor import LOAD_MAGNITUDE_MAX, LOAD_MAX_WORD
    from spindle.native import chain as native_chain

    header = abi.header_constants()
    assert header["PS_LOAD_MAX_WORD"] == LOAD_MAX_WORD
    assert header["PS_LOAD_MAGNITUDE_MAX"] == LOAD_MAGNITUDE_MAX
    assert header["PS_MIN_MOMENT_ARM_M"] == MIN_MOMENT_ARM_M
    assert header["PS_MOMENT_ARM_MAX_POINTS"] == native_chain.MOMENT_ARM_MAX_POINTS
    source = native_chain.config_c_source()
    assert ".gto = {.gain_pps = " + (40.0).hex() in source
    assert ".n_moment_arm_points = 262" in source
