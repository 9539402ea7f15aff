"""The fault-injection soak (proprio_env.experiments.fault_injection, scripts/fault_soak.py):
its stream holds the faults it claims, its checks catch a broken backend, and both backends
pass it."""

from __future__ import annotations

import itertools
import math
from collections import Counter

import numpy as np
import pytest
from work_bounds import count_each_call

from proprio_env.experiments import fault_injection as fi
from spindle.chain import BACKENDS, COUNTERS, ArmChain, ChainConfig, make_chain
from spindle.chain.config import real_array
from spindle.chain.length_model import load_length_fits
from spindle.chain.sensor import is_valid_reading, valid_load_words


def _stream(seed: int, n: int, p: float = 0.5) -> list[fi.Segment]:
    return list(fi.fault_stream(np.random.default_rng(seed), n, load_length_fits(), p))


def test_stream_is_seeded_and_holds_the_documented_faults():
    assert repr(_stream(2, 1_000)) == repr(_stream(2, 1_000))
    assert repr(_stream(2, 1_000)) != repr(_stream(3, 1_000))
    segs = _stream(4, 8_000, 0.8)  # a seed whose 8000 samples hold every entry and fault
    assert 8_000 <= sum(len(s.t_s) for s in segs) < 10_000
    assert set(Counter(s.fault for s in segs)) == {"", *fi.FAULTS}
    assert {s.entry for s in segs} == set(fi.ENTRIES)
    assert {s.single for s in segs if s.fault} == {True, False}  # faults: single and in blocks
    # Clean samples: finite increasing times ~2 ms apart except across dropouts, valid values.
    t = np.array([t for s in segs for t, ok in zip(s.t_s, s.clean, strict=True) if ok])
    assert np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)
    assert np.median(np.diff(t)) == pytest.approx(2e-3, rel=0.05)
    for s in segs:
        for v, ok in zip(s.values, s.clean, strict=True):
            if ok and s.entry == "counts":
                assert is_valid_reading(v)
        # the load words: every counts sample carries one unless the run is load_missing
        assert (s.loads is None) == (s.entry != "counts" or s.fault == "load_missing")
        if s.fault == "load_invalid":
            assert not all(valid_load_words(real_array(s.loads)))
    words = np.array([w for s in segs if s.loads and not s.fault for w in s.loads])
    assert np.mean(valid_load_words(words)) > 0.99 and np.ptp(words[words < 1024]) > 300
    # Dropouts: one sample to minutes, moving ones during a movement.
    gaps = {"dropout_moving": [], "dropout_rest": []}
    angles = np.array([a for s in segs for a in s.true_angle_deg])
    assert angles.min() > 0 and angles.max() < 130
    for prev, s in itertools.pairwise(segs):
        if s.fault in gaps:
            times = [prev.true_t_s[-1], *s.true_t_s]
            gaps[s.fault].append(max(np.diff(times)))
    for name, g in gaps.items():
        assert min(g) < 0.02 and 10.0 < max(g) <= fi.DROPOUT_RANGE_S[1] + 0.01, name


class _Broken(ArmChain):
    """The numpy chain with one bug: every 10th push (block pushes included) reports an NaN
    Ia and counts nothing."""

    pushes = 0
    lost = 0

    @property
    def counters(self):
        counted = super().counters
        counted["accepted"] -= self.lost
        return counted

    def _broken(self, out):
        self.pushes += 1
        if self.pushes % 10 == 0:
            self.lost += 1
            out.ia_pps[0] = math.nan
        return out

    def push_counts(self, t_s, counts, load=None):
        return self._broken(super().push_counts(t_s, counts, load))

    def _block(self, *args):  # every block push
        return self._broken(super()._block(*args))

    def push_angle(self, t_s, angle_deg):
        return self._broken(super().push_angle(t_s, angle_deg))

    def push_lengths(self, t_s, length_L0, angle_deg=None):
        return self._broken(super().push_lengths(t_s, length_L0, angle_deg))


def test_checks_catch_a_broken_backend():
    chains = {"numpy": _Broken(ChainConfig()), "c": make_chain(ChainConfig(backend="c"))}
    report = fi.run_soak(600, seed=3, fault_probability=0.0, chains=chains)
    assert report.samples >= 600
    assert not report.ok and not report.counters_equal
    assert report.nonfinite["numpy"] > 0 and report.nonfinite["c"] == 0
    assert report.counters["numpy"]["accepted"] < report.counters["c"]["accepted"]
    assert "counters_equal=False" in report.last_line()


PUSHES = tuple(f"push_{entry}{block}" for entry in fi.ENTRIES for block in ("", "_block"))
MAX_CALLS_PER_SAMPLE_NUMPY = 8000
"""Function calls per sample of one numpy push (blocks: per sample of the block); measured
(2026-12-02, seed 0 below, the one-arm view of the batched chain with the tendon organs) 1214
median, 6206 at most (a fault's restart: a block that falls back to its columns)."""
MAX_CALLS_PER_PUSH_C = 60
"""Python-side calls of one C push, single or block (one C call): measured 17 median, 45 at
most. The work inside the C call is bounded by PS_CHAIN_MAX_BRIDGE_UPDATES."""


def test_quick_soak_passes_on_both_backends():
    """Both backends through a short faulty stream (every class above, half the runs start
    with a fault): no push raises, counters agree, rates physiological, nothing stuck, and
    every push's work bounded (function calls counted, tests/work_bounds.py; no clock)."""
    chains = {b: make_chain(ChainConfig(backend=b)) for b in BACKENDS}
    calls = {"numpy": count_each_call(chains["numpy"], PUSHES, 64 * MAX_CALLS_PER_SAMPLE_NUMPY),
             "c": count_each_call(chains["c"], PUSHES, MAX_CALLS_PER_PUSH_C)}
    report = fi.run_soak(1500, seed=0, fault_probability=0.5, max_call_s=None, chains=chains)
    assert max(n / samples for n, samples in calls["numpy"]) <= MAX_CALLS_PER_SAMPLE_NUMPY
    assert max(n for n, _ in calls["c"]) <= MAX_CALLS_PER_PUSH_C
    for counted in calls.values():  # every sample went through a counted push
        assert sum(samples for _, samples in counted) == report.samples
    assert set(report.counters) == set(BACKENDS)
    assert set(report.counters["c"]) <= set(COUNTERS)
    assert report.counters["c"]["accepted"] > 1000
    assert report.max_rate_pps["c"] > 10.0  # the spindles fire
    assert report.max_ib_pps["c"] > 10.0  # the tendon organs too
    assert report.faults["load_invalid"] > 0 and report.faults["load_missing"] > 0
    assert report.counters["c"]["invalid_load"] > 10 and report.counters["c"]["missing_load"] > 0
    assert report.max_ib_diff_pps <= fi.IB_DIFF_LIMIT_PPS  # (measured 1e-14)
    assert report.failures == []
    assert report.last_line().startswith(f"fault_soak samples={report.samples} "
                                          "counters_equal=True")


@pytest.mark.slow
def test_soak_quick_mode():
    """What ``python scripts/fault_soak.py --quick`` runs (10^4 samples)."""
    report = fi.run_soak(10_000, seed=0)
    assert report.failures == []


# -- the wrapper section -----------------------------------------------------------------

def test_wrapper_soak_passes_on_both_backends():
    """Both backends, the three wrapper targets, every wrapper fault: nothing non-finite or
    outside the wrapped space, restarts as the rules say, copies equal, refused steps leave
    no trace."""
    from proprio_env.experiments import wrapper_fault_injection as wfi

    report = wfi.run_wrapper_soak(40, seed=0, fault_probability=0.5)
    assert set(report.faults) == set(wfi.WRAPPER_FAULTS)
    assert report.restarts["clock_far"] == report.faults["clock_far"] > 0
    assert report.max_rate_pps > 10.0  # the spindles fire
    # Ib on C equals its numpy twin at every step that reset nothing (measured ~1e-13 pps)
    assert report.ib_twin_steps > 50 and report.ib_twin_max_diff_pps <= wfi.IB_TWIN_TOLERANCE_PPS
    assert report.failures == []
    assert report.last_line().endswith("ok=True")


def test_wrapper_soak_checks_catch_a_copy_that_drifts(monkeypatch):
    """A wrapper whose copies lose their recorded lengths (the fault of issue 28.3,
    re-created) is caught: the copy differs from its original."""
    from proprio_env.experiments import wrapper_fault_injection as wfi
    from proprio_env.wrappers import capture

    def frozen(self, state):
        self.__dict__.update(state)
        self._bind()
        self._length_view = self._length_view.copy()  # a frozen array, as before the fix

    monkeypatch.setattr(capture.PhysicsHook, "__setstate__", frozen)
    monkeypatch.setattr(wfi, "WRAPPER_FAULTS", ("deepcopy",))
    report = wfi.run_wrapper_soak(30, seed=0, fault_probability=0.5, targets=("single",),
                                  backends=("numpy",))
    assert report.copy_mismatches and not report.ok
    assert "copy_mismatches=0" not in report.last_line()


# -- the vector-env section: refused resets between steps --------------------------------------
def test_vector_soak_refuses_every_bad_reset_and_changes_nothing():
    """Both ids beside a twin: every kind of bad reset refused with ValueError/TypeError, and
    the soaked env equal to its twin bit for bit at every step (nothing half-applied)."""
    from proprio_env.experiments import vector_fault_injection as vfi

    for env_id, report in vfi.run_vector_soak(300, seed=2).items():
        assert report.ok, (env_id, report)
        assert all(report.refused.values()), report.refused  # every kind drawn
        assert report.good_resets > 0 and report.steps == 300


def test_vector_soak_catches_a_half_applied_reset(monkeypatch):
    """Put the old fault back (a refused reset that already reset sub-env 0, as the vector
    env once did): the section must see the soaked env leave its twin."""
    from proprio_env.envs.vector import ElbowProprioVectorEnv
    from proprio_env.experiments import vector_fault_injection as vfi

    original = ElbowProprioVectorEnv.reset

    def half_applied(self, *, seed=None, options=None):
        try:
            return original(self, seed=seed, options=options)
        except (ValueError, TypeError):
            self.core.reset(np.array([0]), [np.random.default_rng(12345)])
            raise

    monkeypatch.setattr(ElbowProprioVectorEnv, "reset", half_applied)
    report = vfi.soak_vector_resets("proprio_env/ElbowReach-v1", 200, seed=2)
    assert sum(report.refused.values()) > 0
    assert report.differing_steps > 0 and not report.ok
