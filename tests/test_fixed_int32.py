"""The host side of every fixed-point C entry refuses a value its int32 format cannot hold.

ctypes passes an int32 argument modulo 2^32 without a word, so a value beyond the format
arrived as another, valid-looking one. Each case below was silently wrong before
``abi.checked_int32``: it is checked here against what the same value means in range."""

from __future__ import annotations

import numpy as np
import pytest

import spindle
from spindle.backends import resolve_backend
from spindle.native import abi, fixed
from spindle.native import build as native_build
from spindle.native import stimulation as cstim
from spindle.stimulation import EncoderParams, StimConfig

pytestmark = pytest.mark.skipif(resolve_backend("auto") != "c", reason="no C library here")


def test_checked_int32_names_the_value_and_the_limit():
    np.testing.assert_array_equal(abi.checked_int32([-(2**31 - 1), 0, 2**31 - 1], "x"),
                                  [-(2**31 - 1), 0, 2**31 - 1])
    for bad in (2**31, -(2**31), 2**32 + 5, np.nan, np.inf):
        with pytest.raises(ValueError, match=r"x=.* does not fit an int32 \(\|value\| <= "):
            abi.checked_int32([0, bad], "x")


def test_a_spindle_length_beyond_q24_is_refused_not_wrapped_to_a_valid_one():
    lib = native_build.load("double")
    fixed.declare_fixed(lib, "double")
    plan = fixed.make_plan(lib, spindle.HUMAN, 1e-3, 0.5)
    n = 20
    L = np.full(n, 1.0)
    # 256.5 L0 in Q24 is 2^32 + 0.5 * 2^24: modulo 2^32 it was 0.5 L0, a valid length
    L_wrapping = L.copy()
    L_wrapping[5] = 256.5
    with pytest.raises(ValueError, match=r"L \(Q24 L0\)="):
        fixed.fixed_rates(lib, plan, L_wrapping, np.zeros(n), np.zeros(n))
    with pytest.raises(ValueError, match=r"gs \(Q8 pps\)="):
        fixed.fixed_rates(lib, plan, L, np.zeros(n), np.full(n, 2.0**24))
    # in range, an out-of-model length is the C step's own refusal (a status), as before
    L_long = L.copy()
    L_long[5] = 3.0
    *_, code = fixed.fixed_rates(lib, plan, L_long, np.zeros(n), np.zeros(n))
    assert code != abi.Status.PS_OK


def test_a_stimulator_interval_beyond_int32_us_is_refused():
    config = StimConfig(params=EncoderParams(mode="frequency", seed=1))
    q = cstim.to_q16(np.full((3, config.n_channels), 20.0))
    # 2^32 + 2000 us arrived as 2000 us: a 72-minute hold became a 2 ms one
    with pytest.raises(ValueError, match=r"dt_us="):
        cstim.fixed_run(config, q, np.array([2000, 2**32 + 2000, 2000]))
    with pytest.raises(ValueError, match=r"rates_q16="):
        cstim.fixed_run(config, q.astype(np.int64) + 2**32, np.full(3, 2000))
    events, _ = cstim.fixed_run(config, q, np.full(3, 2000))  # in range it runs
    assert events.dtype == cstim.PULSE_FX_DTYPE
