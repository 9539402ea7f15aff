"""The batched chain: arm k of a ArmChainBatch equals a single ArmChain fed the same samples.

The reference is independent of the batch: N single ``ArmChain`` objects, each fed its arm's
samples one by one (outputs within 1e-9, counters equal), through fault streams that exercise
every handling rule of ``spindle/chain/arm.py`` per arm.
"""

from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest

from spindle import core
from spindle.chain import ArmChain, ChainConfig
from spindle.chain.batch import ArmChainBatch
from spindle.chain.config import COUNTERS, ArmSample
from spindle.chain.length_model import load_length_fits
from spindle.chain.samples import BatchSample

FITS = load_length_fits()
CONFIG = ChainConfig()
FIELDS = ("t_s", "counts", "counts_filtered", "angle_deg", "length_L0", "velocity_L0_s",
          "acceleration_L0_s2", "template_L0", "gamma_static_pps", "gamma_dynamic_pps",
          "ia_pps", "ii_pps")
KINDS = {"counts": "push_counts", "angle": "push_angle", "lengths": "push_lengths"}
RESYNC = CONFIG.resync_after_samples


def assert_arm_equal(got: ArmSample, want: ArmSample, what: str) -> None:
    assert got.accepted == want.accepted, what
    for name in FIELDS:
        np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-9,
                                   atol=1e-9, err_msg=f"{what}: {name}")


def assert_counters_equal(batch: ArmChainBatch, singles: list[ArmChain], what: str) -> None:
    counters = batch.counters
    for k, single in enumerate(singles):
        assert {name: int(counters[name][k]) for name in COUNTERS} == single.counters, \
            f"{what}: arm {k}"


def motion_deg(t: np.ndarray, arm: int) -> np.ndarray:
    """A different movement per arm: its own start, amplitude and frequency."""
    return 20.0 + 18.0 * arm + (25.0 + 5.0 * arm) * np.sin(2 * np.pi * (0.7 + 0.4 * arm) * t
                                                            + arm)


def signal_of(kind: str, angle: np.ndarray) -> np.ndarray:
    if kind == "counts":
        return np.round(CONFIG.calibration.counts(angle))
    if kind == "angle":
        return angle.copy()
    return FITS.length_L0(np.radians(angle), clip=True)


def fault_stream(kind: str, arm: int, n: int, seed: int,
                 jitter_s: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Arm ``arm``'s n samples (times, signal) with its own jitter and faults: NaN and
    out-of-range values, repeated, backwards and NaN times, bridged gaps, long gaps
    (restarts), a corrupt future time followed by true ones (a clock resync after RESYNC
    backwards samples) and slew-limited jumps."""
    rng = np.random.default_rng([seed, arm])
    dt = 0.002 + np.clip(rng.normal(0.0, jitter_s, n), -8e-4, 8e-4)
    true_t = 0.002 * (arm + 1) * 0.1 + np.cumsum(dt)
    t = true_t.copy()
    angle = motion_deg(true_t, arm)
    events = rng.choice(12, size=n, p=[0.79] + [0.021] * 10 + [0.0])
    future = rng.integers(n // 4, n - RESYNC - 2)  # one corrupt clock far ahead per arm
    events[future] = 11
    events[future + 1:future + RESYNC + 1] = 0
    shift = 0.0
    for i in range(1, n):
        e = events[i]
        if e == 3:  # a bridged gap
            shift += 0.012
        elif e == 4:  # a long gap: restart
            shift += 0.2
        t[i] = true_t[i] + shift
        if e == 1:
            t[i] = t[i - 1]  # repeated
        elif e == 2:
            t[i] = t[i - 1] - 0.0007  # backwards
        elif e == 5:
            t[i] = math.nan
        elif e == 6:
            angle[i] += 70.0  # a jump the slew limit holds back
        elif e == 11:
            t[i] += 1e3  # accepted as a long gap; the true times after it are backwards
    x = signal_of(kind, angle)
    bad = np.flatnonzero(events == 7)
    if kind == "counts":
        x[bad] = rng.choice([-1.0, 5000.0, 3.5, math.nan], size=bad.size)
    elif kind == "angle":
        x[bad] = rng.choice([math.nan, math.inf, -math.inf], size=bad.size)
        x[events == 8] = rng.uniform(-40, 170, size=int((events == 8).sum()))  # clamped
    else:
        x[bad] = rng.choice([0.3, 1.7, math.nan], size=(bad.size, 2))
        x[events == 8] += 0.05  # a length jump the slew limit holds back
    return t, x


def make_pair(n: int, config: ChainConfig = CONFIG):
    batch = ArmChainBatch(n, config, FITS)
    singles = [ArmChain(config, FITS) for _ in range(n)]
    start = np.array([5.0 + 25.0 * k for k in range(n)])
    batch.reset(start, t_s=0.0)
    for k, single in enumerate(singles):
        single.reset(start[k], 0.0)
    return batch, singles


def run_streams(kind: str, n: int, samples: int, seed: int, jitter_s: float = 1e-4,
                config: ChainConfig = CONFIG):
    """Push per-arm fault streams (arms active on a random subset of pushes, with switch
    changes and per-arm resets) through a batch and N single chains, comparing every push."""
    batch, singles = make_pair(n, config)
    streams = [fault_stream(kind, k, samples, seed, jitter_s) for k in range(n)]
    position = [0] * n
    rng = np.random.default_rng(seed + 99)
    push = KINDS[kind]
    shape = (n, 2) if kind == "lengths" else (n,)
    for step in range(samples + samples // 4):
        if step % 97 == 50:  # the switch: some arms follow an intended angle
            intended = np.where(rng.random(n) < 0.5, math.nan, rng.uniform(-10, 140, n))
            batch.set_intended_angle(intended)
            for k, single in enumerate(singles):
                single.set_intended_angle(None if np.isnan(intended[k]) else intended[k])
        if step % 131 == 70:  # some arms reset mid-stream (autoreset)
            arms = np.flatnonzero(rng.random(n) < 0.4)
            angle = rng.uniform(-5, 135, arms.size)
            t0 = np.array([streams[k][0][min(position[k], samples - 1)] - 1e-4 for k in arms])
            t0 = np.where(np.isfinite(t0), t0, 0.0)
            out = batch.reset(angle, t_s=t0, arms=arms)
            for i, k in enumerate(arms):
                assert_arm_equal(out.arm(k), singles[k].reset(angle[i], t0[i]), "reset")
            assert not out.accepted[np.setdiff1d(np.arange(n), arms)].any()
        active = np.array([position[k] < samples for k in range(n)]) & (rng.random(n) < 0.8)
        if not active.any():
            if all(p >= samples for p in position):
                break
            continue
        t = np.zeros(n)
        x = np.zeros(shape)
        for k in np.flatnonzero(active):
            t[k], x[k] = streams[k][0][position[k]], streams[k][1][position[k]]
        before = [single.last for single in singles]
        state_before = batch.spindle_state
        counters_before = batch.counters
        out = batch.__getattribute__(push)(t, x, active=None if active.all() else active)
        assert isinstance(out, BatchSample)
        counters_after, state_after = batch.counters, batch.spindle_state
        for k, single in enumerate(singles):
            if active[k]:
                want = getattr(single, push)(t[k], x[k])
                position[k] += 1
            else:  # no sample: untouched, the last output again with accepted False
                want = ArmSample(**{**before[k].__dict__, "accepted": False})
                for name in COUNTERS:
                    assert counters_after[name][k] == counters_before[name][k]
                spindles = [2 * k, 2 * k + 1]
                for name in ("tension_FU", "velocity_root", "activation", "length_L0"):
                    np.testing.assert_array_equal(getattr(state_after, name)[spindles],
                                                  getattr(state_before, name)[spindles])
            assert_arm_equal(out.arm(k), want, f"{kind} step {step} arm {k}")
        assert_counters_equal(batch, singles, f"{kind} step {step}")
    for k, single in enumerate(singles):
        assert_arm_equal(batch.last.arm(k), single.last, f"{kind} last arm {k}")
    return batch, singles


@pytest.mark.parametrize("kind", list(KINDS))
def test_fault_streams_equal_single_chains(kind):
    batch, _singles = run_streams(kind, n=5, samples=260, seed=3)
    totals = {name: int(batch.counters[name].sum()) for name in COUNTERS}
    # every rule was exercised (by several arms)
    for name in ("accepted", "repeated_time", "time_backwards", "bad_time", "gaps",
                 "slew_limited", "restarts", "clock_resyncs"):
        assert totals[name] > 0, (name, totals)
    invalid = {"counts": "invalid_reading", "angle": "invalid_angle",
               "lengths": "invalid_length"}[kind]
    assert totals[invalid] > 0
    if kind != "lengths":
        assert totals["angle_clamped"] > 0


@pytest.mark.parametrize("kind", list(KINDS))
def test_shared_times_equal_single_chains(kind):
    """Arms that share their sample times (a physics step) take the one-group path."""
    run_streams(kind, n=6, samples=90, seed=11, jitter_s=0.0)


def test_one_arm_is_the_single_chain_bit_for_bit():
    batch, (single,) = make_pair(1)
    t, x = fault_stream("lengths", 0, 300, seed=5, jitter_s=0.0)
    for i in range(t.size):
        got, want = batch.push_lengths(t[i:i + 1], x[i:i + 1]).arm(0), single.push_lengths(
            t[i], x[i])
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name), name)


def test_unfiltered_config_equals_single_chains():
    run_streams("angle", n=3, samples=120, seed=8, config=ChainConfig(lowpass_hz=None))


@pytest.mark.parametrize("kind", list(KINDS))
def test_ragged_blocks_equal_single_chains(kind, monkeypatch):
    # jittered arms: each arm its own sub-step size, the core's step size per spindle
    calls = []
    advance = core.advance
    monkeypatch.setattr(core, "advance", lambda *a: calls.append(np.ndim(a[4])) or advance(*a))
    n, k = 5, 12
    batch, singles = make_pair(n)
    streams = [fault_stream(kind, a, 10 * k, seed=21) for a in range(n)]
    rng = np.random.default_rng(4)
    position = [0] * n
    push_block = KINDS[kind] + "_block"
    for block in range(9):
        count = rng.integers(0, k + 1, n)
        count[block % n] = 0  # an arm without a sample in this block
        t = np.full((n, k), math.nan)
        x = np.full((n, k, 2) if kind == "lengths" else (n, k), math.nan)  # NaN padding
        for a in range(n):
            p = position[a]
            t[a, :count[a]] = streams[a][0][p:p + count[a]]
            x[a, :count[a]] = streams[a][1][p:p + count[a]]
            position[a] += count[a]
        before = [single.last for single in singles]
        out = getattr(batch, push_block)(t, x, n_samples=count)
        for a, single in enumerate(singles):
            if count[a]:
                want = getattr(single, push_block)(t[a, :count[a]], x[a, :count[a]])
            else:
                want = ArmSample(**{**before[a].__dict__, "accepted": False})
            assert_arm_equal(out.arm(a), want, f"block {block} arm {a}")
        assert_counters_equal(batch, singles, f"block {block}")
    # without n_samples every arm pushes the whole block
    t = np.stack([streams[a][0][position[a]:position[a] + 3] for a in range(n)])
    x = np.stack([streams[a][1][position[a]:position[a] + 3] for a in range(n)])
    out = getattr(batch, push_block)(t, x)
    for a, single in enumerate(singles):
        assert_arm_equal(out.arm(a), getattr(single, push_block)(t[a], x[a]), f"arm {a}")
    assert_counters_equal(batch, singles, "full block")
    assert 1 in calls, "no step with a step size per spindle"


def _snapshot(batch: ArmChainBatch):
    return pickle.dumps((batch.counters, batch.last, batch.spindle_state, batch._median.snapshot(),
                         batch._fusimotor.predictor.snapshot(), batch._behind, batch._t))


def _failing_advance(monkeypatch, after_calls: int):
    """core.advance and core.plain_advance raise after ``after_calls`` calls of either."""
    calls = {"n": 0}

    def failing(real):
        def advance(*args, **kwargs):
            calls["n"] += 1
            if calls["n"] > after_calls:
                raise FloatingPointError("injected failure")
            return real(*args, **kwargs)
        return advance

    real = {name: getattr(core, name) for name in ("advance", "plain_advance")}
    for name, step in real.items():
        monkeypatch.setattr(core, name, failing(step))

    def undo():
        for name, step in real.items():
            monkeypatch.setattr(core, name, step)

    return undo


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize(("n", "after_calls"), [(5, 0), (5, 1), (5, 3), (3, 2)])
def test_a_failed_push_leaves_every_arm_as_it_was(monkeypatch, kind, n, after_calls):
    batch, _ = make_pair(n)
    streams = [fault_stream(kind, a, 60, seed=2) for a in range(n)]
    for i in range(40):  # some history: rejects, a restart maybe, a full median window
        batch.__getattribute__(KINDS[kind])(np.array([s[0][i] for s in streams]),
                                            np.array([s[1][i] for s in streams]))
    reference = copy.deepcopy(batch)
    before = _snapshot(batch)
    # jittered times: several groups of sub-steps, each arm its own sub-step size, so a
    # later step fails after earlier ones have been written
    t = np.array([s[0][40] for s in streams]) + 0.0003 * np.arange(n)
    x = np.array([s[1][40] for s in streams])
    undo = _failing_advance(monkeypatch, after_calls)
    with pytest.raises(FloatingPointError):
        batch.__getattribute__(KINDS[kind])(t, x)
    with pytest.raises(FloatingPointError):  # and a block (atomic as a whole)
        batch.__getattribute__(KINDS[kind] + "_block")(
            np.stack([s[0][40:46] for s in streams]), np.stack([s[1][40:46] for s in streams]))
    undo()
    assert _snapshot(batch) == before
    for i in range(40, 60):
        t = np.array([s[0][i] for s in streams])
        x = np.array([s[1][i] for s in streams])
        got = batch.__getattribute__(KINDS[kind])(t, x)
        want = reference.__getattribute__(KINDS[kind])(t, x)
        for name in (*FIELDS, "accepted"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert _snapshot(batch) == _snapshot(reference)


def test_a_failed_reset_changes_nothing():
    batch, _ = make_pair(3)
    batch.push_angle(np.full(3, 0.002), np.array([10.0, 20.0, 30.0]))
    before = _snapshot(batch)
    with pytest.raises(ValueError, match="arm 2"):
        batch.reset(np.array([10.0, math.nan]), t_s=1.0, arms=np.array([0, 2]))
    with pytest.raises(ValueError, match="length_L0 of arm 1"):
        batch.reset(np.array([10.0, 20.0]), length_L0=np.array([[1.0, 1.0], [0.2, 1.0]]),
                    arms=np.array([0, 1]))
    with pytest.raises(ValueError, match="twice"):
        batch.reset(np.array([10.0, 20.0]), arms=np.array([1, 1]))
    with pytest.raises(ValueError, match=r"0\.\.2"):
        batch.reset(np.array([10.0]), arms=np.array([3]))
    with pytest.raises(ValueError, match="t_s of arm 1"):
        batch.reset(np.array([10.0, 20.0, 30.0]), t_s=np.array([0.0, math.inf, 0.0]))
    assert _snapshot(batch) == before


def test_reset_with_exact_lengths_equals_single_chain():
    batch, singles = make_pair(3)
    L = np.array([[0.9, 1.1], [1.0, 1.0], [1.2, 0.8]])
    angle = np.array([30.0, 200.0, -20.0])  # only recorded with exact lengths
    out = batch.reset(angle, t_s=np.array([0.5, 0.6, 0.7]), length_L0=L)
    for k, single in enumerate(singles):
        assert_arm_equal(out.arm(k), single.reset(angle[k], 0.5 + 0.1 * k, L[k]), "reset")
    t = np.array([0.7, 0.5, 0.8])  # arm 1 behind its reset time: rejected
    for i in range(30):
        t = t + 0.002
        x = L + 0.002 * i
        out = batch.push_lengths(t, x)
        for k, single in enumerate(singles):
            assert_arm_equal(out.arm(k), single.push_lengths(t[k], x[k]), f"{i} {k}")
    assert_counters_equal(batch, singles, "lengths")


def test_shape_errors_name_the_argument():
    batch, _ = make_pair(4)
    with pytest.raises(ValueError, match=r"t_s has shape \(3,\); expected \(4,\)"):
        batch.push_angle(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match=r"angle_deg has shape \(4, 1\)"):
        batch.push_angle(np.zeros(4), np.zeros((4, 1)))
    with pytest.raises(ValueError, match=r"length_L0 has shape \(4, 3\); expected \(4, 2\)"):
        batch.push_lengths(np.zeros(4), np.ones((4, 3)))
    with pytest.raises(ValueError, match=r"counts has shape \(4,\); expected \(4, 5\)"):
        batch.push_counts_block(np.zeros((4, 5)), np.zeros(4))
    with pytest.raises(ValueError, match=r"t_s has shape \(5,\); expected \(4, k\)"):
        batch.push_counts_block(np.zeros(5), np.zeros((4, 5)))
    with pytest.raises(ValueError, match="active has shape"):
        batch.push_angle(np.ones(4), np.ones(4), active=np.ones(4))
    with pytest.raises(ValueError, match="active has shape"):
        batch.push_angle(np.ones(4), np.ones(4), active=np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match=r"n_samples must lie in 0\.\.5"):
        batch.push_angle_block(np.ones((4, 5)), np.ones((4, 5)), n_samples=np.array([1, 2, 6, 0]))
    with pytest.raises(ValueError, match="n_samples has shape"):
        batch.push_angle_block(np.ones((4, 5)), np.ones((4, 5)), n_samples=np.ones(4))
    with pytest.raises(ValueError, match=r"angle_deg has shape \(3,\); expected \(4,\)"):
        batch.reset(np.zeros(3))
    with pytest.raises(ValueError, match=r"angle_deg has shape \(2,\)"):
        batch.set_intended_angle(np.zeros(2))
    with pytest.raises(ValueError, match="n_arms=0"):
        ArmChainBatch(0)
    with pytest.raises(ValueError, match="make_batched_chain"):
        ArmChainBatch(2, ChainConfig(backend="c"))


def test_pushes_need_a_reset_and_outputs_are_read_only():
    batch = ArmChainBatch(2, CONFIG, FITS)
    with pytest.raises(RuntimeError, match="reset"):
        batch.push_angle(np.ones(2), np.ones(2))
    with pytest.raises(RuntimeError, match="reset"):
        batch.last  # noqa: B018
    out = batch.reset(np.array([30.0]), arms=np.array([1]))
    assert out.accepted.tolist() == [False, True]
    with pytest.raises(RuntimeError, match=r"arms \[0\]"):
        batch.push_angle(np.ones(2), np.ones(2))
    out = batch.push_angle(np.ones(2), np.full(2, 31.0), active=np.array([False, True]))
    assert out.accepted.tolist() == [False, True]
    with pytest.raises(ValueError):
        out.ia_pps[0, 0] = 1.0
    assert np.all(np.isfinite(out.ia_pps[1]))


def test_intended_angle_rejects_infinite_values():
    batch, _ = make_pair(2)
    with pytest.raises(ValueError, match="arm 1"):
        batch.set_intended_angle(np.array([30.0, math.inf]))


@pytest.mark.parametrize("how", ["pickle", "deepcopy"])
def test_copies_continue_identically(how):
    batch, _ = make_pair(4)
    streams = [fault_stream("counts", a, 120, seed=9) for a in range(4)]
    batch.set_intended_angle(np.array([math.nan, 50.0, math.nan, 90.0]))
    for i in range(60):
        batch.push_counts(np.array([s[0][i] for s in streams]),
                          np.array([s[1][i] for s in streams]))
    clone = pickle.loads(pickle.dumps(batch)) if how == "pickle" else copy.deepcopy(batch)
    for i in range(60, 120):
        t = np.array([s[0][i] for s in streams])
        x = np.array([s[1][i] for s in streams])
        got, want = clone.push_counts(t, x), batch.push_counts(t, x)
        for name in (*FIELDS, "accepted"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert {k: v.tolist() for k, v in clone.counters.items()} == {
        k: v.tolist() for k, v in batch.counters.items()}


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(KINDS))
def test_long_fault_streams_equal_single_chains(kind):
    run_streams(kind, n=12, samples=3000, seed=31)


def test_jittered_arms_with_different_sub_step_counts_equal_single_chains(monkeypatch):
    """Each arm its own interval (1-4 sub-steps of its own size): arms with fewer sub-steps
    wait while the others step, in one core call per sub-step; still each single chain."""
    partial = []
    commit = core.commit
    monkeypatch.setattr(core, "commit", lambda *a, where=None: partial.append(
        where is not None) or commit(*a, where=where))
    n = 6
    batch, singles = make_pair(n)
    rng = np.random.default_rng(3)
    start = 40.0 + 30.0 * rng.random(n)
    batch.reset(start)
    for a, single in enumerate(singles):
        single.reset(float(start[a]))
    t = np.zeros(n)
    for i in range(150):
        t = t + rng.uniform(0.0012, 0.0035, n)
        counts = np.round(CONFIG.calibration.counts(start + 20.0 * np.sin(2 * np.pi * t)))
        out = batch.push_counts(t, counts)
        for a, single in enumerate(singles):
            assert_arm_equal(out.arm(a), single.push_counts(float(t[a]), float(counts[a])),
                             f"sample {i} arm {a}")
    assert_counters_equal(batch, singles, "end")
    assert any(partial), "no arm waited for the others"


@pytest.mark.parametrize("shape", [(), (1,), (64,), (7, 5)])
def test_length_fits_evaluate_every_muscle_in_one_pass_with_each_fits_bits(shape):
    """LengthFits.length_L0 (one Clenshaw pass over zero-padded coefficient columns) equals
    each muscle's own LengthFit.length_L0, bit for bit, including the range ends."""
    lo, hi = FITS.valid_range_rad
    assert len({len(f.coefficients) for f in FITS.fits}) > 1  # the padding is exercised
    angle = np.random.default_rng(len(shape)).uniform(lo, hi, shape)
    if angle.size > 2:
        angle.flat[:2] = lo, hi
    got = FITS.length_L0(angle)
    want = np.stack([fit.length_L0(angle) for fit in FITS.fits], axis=-1)
    assert got.shape == (*shape, 2)
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("kind", list(KINDS))
@pytest.mark.parametrize("lowpass_hz", [20.0, None])
def test_block_pass_equals_single_chains(kind, lowpass_hz, monkeypatch):
    """Blocks the one-pass path takes (increasing times, bridged gaps; bad values, slew
    jumps, clamped angles, ragged counts, arms without samples, the switch): no column is
    stepped alone, and every arm equals its single chain."""
    config = ChainConfig(lowpass_hz=lowpass_hz)
    columns = []
    column = ArmChainBatch._column
    monkeypatch.setattr(ArmChainBatch, "_column",
                        lambda self, *a: columns.append(1) or column(self, *a))
    n, k, blocks = 6, 11, 12
    batch, singles = make_pair(n, config)
    rng = np.random.default_rng(31)
    true_t = np.cumsum(0.002 + np.clip(rng.normal(0, 2e-4, (n, k * blocks)), -8e-4, 8e-4),
                       axis=1)
    true_t[:, k * 5:] += 0.015  # a bridged gap
    x = np.stack([signal_of(kind, motion_deg(true_t[a], a)) for a in range(n)])
    for a in range(n):
        for i in rng.choice(k * blocks, 8, replace=False):
            if kind == "counts":
                x[a, i] = rng.choice([-1.0, 5000.0, 3.5, math.nan, x[a, i] + 40])
            elif kind == "angle":
                x[a, i] = rng.choice([math.nan, math.inf, x[a, i] + 70.0, 175.0, -30.0])
            else:
                x[a, i] = [rng.choice([0.3, 1.7, math.nan]), x[a, i, 1] + 0.05][rng.integers(2)]
    position = np.zeros(n, dtype=int)
    for block in range(blocks):
        if block == 4:
            intended = np.array([math.nan, 30.0, math.nan, 100.0, math.nan, 60.0])
            batch.set_intended_angle(intended)
            for a, single in enumerate(singles):
                single.set_intended_angle(None if np.isnan(intended[a]) else intended[a])
        count = rng.integers(k - 2, k + 1, n)
        count[block % n] = 0
        t = np.full((n, k), math.nan)
        xs = np.full((n, k, 2) if kind == "lengths" else (n, k), math.nan)
        for a in range(n):
            p = position[a]
            t[a, :count[a]] = true_t[a, p:p + count[a]]
            xs[a, :count[a]] = x[a, p:p + count[a]]
        position += count
        before = [single.last for single in singles]
        out = getattr(batch, KINDS[kind] + "_block")(t, xs, n_samples=count)
        for a, single in enumerate(singles):
            if count[a]:
                want = getattr(single, KINDS[kind] + "_block")(t[a, :count[a]],
                                                               xs[a, :count[a]])
            else:
                want = ArmSample(**{**before[a].__dict__, "accepted": False})
            assert_arm_equal(out.arm(a), want, f"block {block} arm {a}")
        assert_counters_equal(batch, singles, f"block {block}")
    assert not columns, "a block fell back to stepping its columns"
    counters = batch.counters
    assert counters["slew_limited"].sum() > 0
    assert counters["invalid_" + {"counts": "reading", "angle": "angle",
                                  "lengths": "length"}[kind]].sum() > 0
