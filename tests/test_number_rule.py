"""The project's one number rule (:mod:`spindle.number_rule`) where numbers come in.

Strings, bytes, bools and complex numbers used to be taken as numbers: ``dt=True`` ran a 1 s
interval, complex lengths lost their imaginary part, ``ChainConfig(step_s='0.001')`` built a
chain, and the chain accepted ``"500"`` as a reading. A float32 step size left float32
constants in the numpy core's cache that broke every later float64 step of the same size.
Each test below fails on the revision before this rule (33f279b).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

import spindle
from spindle import core
from spindle.chain import BACKENDS, ChainConfig, make_batched_chain, make_chain
from spindle.chain.fusimotor import FusimotorParams
from spindle.chain.sensor import Calibration, EncoderParams
from spindle.fibre_constants import columns, spindle_step_constants, step_constants
from spindle.native import build
from spindle.number_rule import NumberError, real_array, real_scalar, sample_array
from spindle.params import FibreParams

try:
    build.find_compiler()
    BACKEND_PARAMS = list(BACKENDS)
except build.CBackendError:  # pragma: no cover - CI has a compiler
    BACKEND_PARAMS = ["numpy"]

NOT_NUMBERS = [True, np.True_, "0.001", b"0.001", 1e-3 + 0j, np.complex128(1e-3), None,
               [1e-3], np.array([1e-3])]
"""Values that are not one real number; each is something float() or numpy would take."""
NUMBERS = [2, 2.0, np.float32(2.0), np.int64(2), np.array(2.0)]


# -- the rule itself -------------------------------------------------------------------------
@pytest.mark.parametrize("value", NOT_NUMBERS, ids=repr)
def test_a_scalar_that_is_not_a_real_number_is_refused_by_name(value):
    with pytest.raises(NumberError, match=r"^step_s=.* must be a real number \(got ") as info:
        real_scalar("step_s", value)
    # one error that both TypeError and ValueError handlers catch
    assert isinstance(info.value, TypeError) and isinstance(info.value, ValueError)


@pytest.mark.parametrize("value", NUMBERS, ids=repr)
def test_real_scalars_of_every_kind_become_python_floats(value):
    x = real_scalar("x", value, low=0.0, low_open=True)
    assert type(x) is float and x == 2.0


def test_limits_and_overflow_are_named():
    with pytest.raises(NumberError, match=r"x=-1 must be a finite real number >= 0$"):
        real_scalar("x", -1, low=0.0)
    with pytest.raises(NumberError, match=r"x=nan must be a finite real number in \[0, 1\]"):
        real_scalar("x", math.nan, low=0.0, high=1.0)
    with pytest.raises(NumberError, match="is too large"):
        real_scalar("x", 10**400)


@pytest.mark.parametrize("value", [
    ["1.0", "1.0"], np.array(["1.0"]), [b"1"], [True, 1.0], np.array([True, False]),
    [1.0, 1 + 0j], np.array([1.0], dtype=complex), [1.0, None], np.array([1.0], dtype=object),
], ids=repr)
def test_an_array_holding_anything_but_real_numbers_is_refused(value):
    with pytest.raises(NumberError, match=r"^length=.* must hold real numbers only \((it "
                       r"holds .*, a (str|bytes|bool|complex|NoneType)|got an array of dtype)"):
        real_array("length", value)
    # the samples' form: NaN in its place, the real numbers kept
    whole = isinstance(value, np.ndarray) and value.dtype.kind in "bUSc"
    expected = [math.nan if whole or isinstance(v, bool | str | bytes | complex | type(None))
                else float(v)
                for v in np.asarray(value, dtype=object).ravel()]
    np.testing.assert_array_equal(sample_array(value).ravel(), expected)


def test_real_arrays_become_float64():
    for value in ([1, 2.0, np.float32(3)], np.arange(3, dtype=np.int16),
                  np.ones(2, np.float32), [[1.0, 2.0]]):
        x = real_array("x", value)
        assert x.dtype == np.float64
        np.testing.assert_array_equal(x, np.asarray(value, dtype=np.float64))


# -- spindle.simulate and spindle.step, both backends ---------------------------------------
L = 1.0 + 0.01 * np.sin(np.arange(20) / 3.0)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
@pytest.mark.parametrize(("argument", "value"), [
    ("dt", True), ("dt", np.True_), ("dt", "0.001"), ("dt", b"0.001"), ("dt", [1e-3]),
    ("dt", 1e-3 + 0j), ("dt", None), ("step", "0.001"), ("step", True),
    ("length", L.astype(str)), ("length", L.astype(complex)), ("length", [*L[:-1], True]),
    ("gamma_dyn", "50"), ("gamma_stat", np.full(L.shape, True)), ("velocity", L.astype(str)),
    ("acceleration", L + 0j), ("chunk_samples", True), ("chunk_samples", "5"),
    ("chunk_samples", 5.0),
], ids=lambda x: x if isinstance(x, str) and len(x) < 20 else type(x).__name__)
def test_simulate_refuses_values_that_are_not_numbers(backend, argument, value):
    kwargs = {"length": L, "dt": 5e-3, "velocity": np.zeros_like(L)}
    kwargs[argument] = value
    pattern = rf"^{argument}\b.* must (be a real number|hold real numbers only|be an integer)"
    with pytest.raises(NumberError, match=pattern):
        spindle.simulate(backend=backend, **kwargs)


@pytest.mark.parametrize(("argument", "value"), [
    ("dt_s", True), ("dt_s", "0.001"), ("length_L0", "1.0"), ("gamma_dyn_pps", 10 + 0j),
    ("gamma_stat_pps", [True, True]),
])
def test_step_refuses_values_that_are_not_numbers_and_leaves_the_state(argument, value):
    state = spindle.equilibrium_state(np.array([1.0, 1.0]), 10.0, 10.0)
    before = state.copy()
    args = {"length_L0": 1.0, "gamma_dyn_pps": 10.0, "gamma_stat_pps": 10.0, "dt_s": 1e-3,
            argument: value}
    with pytest.raises(NumberError, match=rf"^{argument}\b"):
        spindle.step(state, **args)
    for a, b in zip(state._arrays(), before._arrays(), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(NumberError, match="length_L0"):
        spindle.equilibrium_state(["1.0"], 10.0, 10.0)


# -- 28.1: a float32 step size and the cached step constants --------------------------------
@pytest.mark.parametrize("n", [2, 9, 300], ids=["floats", "floats-9", "numpy-blocks"])
@pytest.mark.parametrize("method", ["trapezoidal", "backward_euler"])
def test_a_float32_step_leaves_no_float32_constants_behind(n, method):
    """``np.float32(1e-3) == 1e-3`` is True under numpy's rules (the float is cast down), so
    the cache handed the float32 call's constants to the next float64 call: the Newton
    iteration, in float32, then failed to converge (9 spindles at 50 pps). The float64 run
    after a float32 one must equal the float64 run in a fresh cache, bit for bit, and the
    float32 run must be the float64 run at float64(float32(1e-3)) s."""
    rng = np.random.default_rng(n)
    lengths = 1.0 + 0.01 * rng.random((9, n))
    c = columns(spindle.CAT)

    def run(dt):
        return spindle.simulate(lengths, dt, gamma_dyn=50.0, gamma_stat=50.0, method=method)

    c.step_constants = c.spindle_step_constants = None
    fresh = run(1e-3)
    c.step_constants = c.spindle_step_constants = None
    at32 = run(np.float32(1e-3))
    after = run(1e-3)
    np.testing.assert_array_equal(after.ia, fresh.ia)
    np.testing.assert_array_equal(after.ii, fresh.ii)
    c.step_constants = c.spindle_step_constants = None
    wide = run(float(np.float32(1e-3)))
    np.testing.assert_array_equal(at32.ia, wide.ia)
    np.testing.assert_array_equal(at32.ii, wide.ii)


def test_the_step_caches_key_on_python_floats():
    c = columns(spindle.CAT)
    k32 = step_constants(c, np.float32(1e-3), np.float32(0.5))
    assert type(k32.h) is float and k32.h == float(np.float32(1e-3))
    assert all(type(f.inv_a2) is float for f in k32.fibre)
    k64 = step_constants(c, 1e-3, 0.5)
    assert k64 is not k32 and k64.h == 1e-3
    per32 = spindle_step_constants(c, np.full(4, 1e-3, np.float32), 0.5)
    assert per32.h.dtype == np.float64
    per64 = spindle_step_constants(c, np.full(4, 1e-3), 0.5)
    assert per64 is not per32 and np.all(per64.h == 1e-3)
    # the chains' and the wrappers' path: core.advance with a float32 step, then a float64 one
    state = spindle.equilibrium_state(np.full(3, 1.0), 50.0, 50.0, params=spindle.CAT)
    L1, g = np.full(3, 1.004), np.full(3, 50.0)
    core.advance(state, L1, g, g, np.float32(1e-3), 0.5, c)
    after = core.advance(state, L1, g, g, 1e-3, 0.5, c)
    c.step_constants = None
    fresh = core.advance(state, L1, g, g, 1e-3, 0.5, c)
    for a, b in zip(after, fresh, strict=True):
        np.testing.assert_array_equal(a, b)


# -- the chain's settings --------------------------------------------------------------------
@pytest.mark.parametrize(("field", "value"), [
    ("step_s", "0.001"), ("step_s", True), ("max_bridge_s", "0.05"), ("max_gap_s", b"0.014"),
    ("max_speed_deg_s", "1000"), ("max_speed_L0_s", "8"), ("max_speed_L0_s", True),
    ("lowpass_hz", "5"), ("lowpass_hz", 20 + 0j), ("median_window", "7"),
    ("median_window", np.True_), ("resync_after_samples", 7.0),
])
def test_chain_config_refuses_values_that_are_not_numbers(field, value):
    with pytest.raises(NumberError, match=rf"^{re.escape(f'{field}={value!r}')} must be "
                                          "(a real number|an integer)"):
        ChainConfig(**{field: value})


def test_chain_config_keeps_numpy_numbers_as_python_numbers():
    config = ChainConfig(step_s=np.float32(5e-4), max_bridge_s=np.float64(0.04),
                         median_window=np.int64(5), lowpass_hz=np.int32(15))
    assert type(config.step_s) is float and config.step_s == float(np.float32(5e-4))
    assert type(config.median_window) is int and config.median_window == 5
    assert type(config.lowpass_hz) is float and config.lowpass_hz == 15.0
    assert config == ChainConfig(step_s=float(np.float32(5e-4)), max_bridge_s=0.04,
                                 median_window=5, lowpass_hz=15.0)


@pytest.mark.parametrize(("make", "field"), [
    (lambda: EncoderParams(max_count=True), "max_count"),
    (lambda: EncoderParams(sample_rate_hz="500"), "sample_rate_hz"),
    (lambda: EncoderParams(invalid_rate=0.1j), "invalid_rate"),
    (lambda: Calibration(sign=True), "sign"),
    (lambda: Calibration(zero_count="290"), "zero_count"),
    (lambda: FusimotorParams(delay_s="0.04"), "delay_s"),
    (lambda: FusimotorParams(predictor_rate_hz=True), "predictor_rate_hz"),
    (lambda: FibreParams(tau_s="0.1"), "tau_s"),
    (lambda: spindle.SpindleParams(spindle.CAT.bag1, spindle.CAT.bag2, spindle.CAT.chain,
                                   S="0.156"), "S"),
])
def test_the_chain_parameter_sets_refuse_values_that_are_not_numbers(make, field):
    with pytest.raises(NumberError, match=rf"^{field}="):
        make()


# -- the chain's samples: rejected and counted, like NaN, at every entry point --------------
BAD_SAMPLES = ["500", b"500", True, np.True_, None]
SAMPLE_CASES = [  # (push, counter, t, value) with one bad field
    ("push_counts", "invalid_reading", 0.002, "reading"),
    ("push_counts", "bad_time", "t", 500.0),
    ("push_angle", "invalid_angle", 0.002, "angle"),
    ("push_angle", "bad_time", "t", 40.0),
    ("push_lengths", "invalid_length", 0.002, "lengths"),
]


def _bad(value, slot):
    return [value, 1.0] if slot == "lengths" else value


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
@pytest.mark.parametrize("bad", BAD_SAMPLES, ids=repr)
def test_a_sample_that_is_not_a_number_is_rejected_and_counted(backend, bad):
    """docs/faults.md: a reading, angle, length or time that is not one real number is
    rejected (the output repeats, ``accepted`` False) and counted like NaN; "500" and True
    were accepted as 500 counts and 1 s."""
    chain = make_chain(ChainConfig(backend=backend))
    chain.reset(40.0, 0.0)
    before = chain.last
    for push, counter, t, value in SAMPLE_CASES:
        t = bad if t == "t" else t
        value = _bad(bad, value) if isinstance(value, str) else value
        was = chain.counters[counter]
        out = getattr(chain, push)(t, value)
        assert not out.accepted and chain.counters[counter] == was + 1, (push, counter)
        np.testing.assert_array_equal(out.ia_pps, before.ia_pps)
    assert chain.counters["accepted"] == 0
    # in a block, such a sample is counted on its own and the real ones go through
    chain.push_angle_block([0.002, 0.004, bad, 0.006], [40.0, bad, 40.0, 40.0])
    assert chain.counters["accepted"] == 2
    chain.push_counts_block([0.008, 0.010], np.array([bad, 500], dtype=object))
    assert chain.counters["accepted"] == 3 and chain.counters["invalid_reading"] == 2
    with pytest.raises(ValueError, match="finite real number"):
        chain.reset(bad, 0.0)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
def test_the_batched_chain_rejects_and_counts_them_per_arm_like_nan(backend):
    """Arms 1-3 get a string, a bool and bytes (or complex) where arm 0 gets a number; a
    second chain gets NaN there. Counters, ``accepted`` and outputs must be the same."""
    chains = [make_batched_chain(4, ChainConfig(backend=backend)) for _ in range(2)]
    for chain in chains:
        chain.reset(np.full(4, 40.0), 0.0)

    def both(push, *columns, bad):
        first = None
        for chain, nan in zip(chains, (False, True), strict=True):
            args = [np.array([c[0], *([math.nan] * 3 if nan and i == bad else c[1:])],
                             dtype=object) for i, c in enumerate(columns)]
            out = getattr(chain, push)(*args)
            if nan:
                np.testing.assert_array_equal(out.accepted, first.accepted)
                np.testing.assert_array_equal(out.ia_pps, first.ia_pps)
            first = out
        for name, value in chains[0].counters.items():
            np.testing.assert_array_equal(value, chains[1].counters[name], err_msg=name)
        return first

    t = [0.002] * 4
    both("push_counts", t, [500, "500", True, b"500"], bad=1)
    both("push_angle", [0.004, "0.004", np.True_, None], [40.0] * 4, bad=0)
    both("push_angle", [0.006] * 4, [40.0, "40", True, 40 + 0j], bad=1)
    counters = chains[0].counters
    np.testing.assert_array_equal(counters["invalid_reading"], [0, 1, 1, 1])
    np.testing.assert_array_equal(counters["bad_time"], [0, 1, 1, 1])
    np.testing.assert_array_equal(counters["invalid_angle"], [0, 1, 1, 1])
    np.testing.assert_array_equal(counters["accepted"], [3, 0, 0, 0])
    # the block pushes: the same counters as NaN in those places
    chain = chains[0]
    chain.push_counts_block(np.full((4, 1), 0.008),
                            np.array([[500], ["500"], [True], [None]], dtype=object))
    np.testing.assert_array_equal(chain.counters["invalid_reading"], [0, 2, 2, 2])
    chain.push_lengths_block(np.full((4, 1), 0.010), np.array(
        [[[0.9, 1.0]], [["0.9", 1.0]], [[True, 1.0]], [[0.9, 1j]]], dtype=object))
    np.testing.assert_array_equal(chain.counters["invalid_length"], [0, 1, 1, 1])
    np.testing.assert_array_equal(chain.counters["accepted"], [5, 0, 0, 0])


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
@pytest.mark.parametrize("bad", ["60", True, b"60", None, 60 + 0j], ids=repr)
def test_an_intended_angle_that_is_not_a_number_raises_at_every_entry(backend, bad):
    """The switch is a setting, not a sample: it raises. The C chains took "60" as 60 deg,
    the numpy batch took it as NaN (the measured motion), ``run_trace`` raised a bare
    TypeError."""
    config = ChainConfig(backend=backend)
    chain = make_chain(config)
    chain.reset(40.0, 0.0)
    if bad is not None:  # None is the switch's "measured motion"
        with pytest.raises(ValueError, match="angle_deg"):
            chain.set_intended_angle(bad)
    t = np.arange(1, 4) * 0.002
    with pytest.raises(NumberError, match="intended_angle_deg"):
        chain.run_trace("push_angle", t, np.full(3, 40.0), [60.0, bad, 60.0])
    assert chain.counters["accepted"] == 0
    batch = make_batched_chain(3, config)
    batch.reset(np.full(3, 40.0), 0.0)
    with pytest.raises(NumberError, match="angle_deg"):
        batch.set_intended_angle(np.array([60.0, bad, math.nan], dtype=object))
    batch.set_intended_angle(np.array([60.0, math.nan, 70]))  # numbers and NaN still do


def test_the_wrappers_bank_takes_its_step_by_the_rule():
    from proprio_env.wrappers.bank import SpindleDriver

    def bank(**kwargs):
        return SpindleDriver(2, np.array([0.8, 0.9]), np.array([1.1, 1.2]), **kwargs)

    assert type(bank(step_s=np.float32(5e-4)).step_s) is float
    assert bank(step_s=np.float32(5e-4)).step_s == float(np.float32(5e-4))
    for field, value in (("step_s", "0.001"), ("step_s", True), ("max_speed_L0_s", "8"),
                         ("max_speed_L0_s", 8 + 0j)):
        with pytest.raises(NumberError, match=rf"^{field}="):
            bank(**{field: value})
