"""The C tendon organ (double and fixed point) against the numpy step and the reference."""

from __future__ import annotations

import numpy as np
import pytest

from spindle import tendon_organ as gto
from spindle.backends import resolve_backend
from spindle.native import abi
from spindle.native import tendon_organ as cgto
from spindle.tendon_organ_params import (
    ARM26_MAX_ISOMETRIC_FORCE_N,
    CAT,
    HUMAN,
    MAX_FORCE_N,
    force_scales_N,
)
from spindle.tendon_organ_reference import reference_rates

pytestmark = pytest.mark.skipif(resolve_backend("auto") != "c", reason="no C library here")

G2_ARM = force_scales_N(HUMAN, [ARM26_MAX_ISOMETRIC_FORCE_N[m] for m in ("BRA", "TRImed")])


def random_forces(seed: int, shape: tuple[int, int], scale: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = np.abs(np.cumsum(rng.normal(0, scale, shape), axis=0))
    f[shape[0] // 3] = -5.0  # a slack sample
    return f


@pytest.mark.parametrize("h", [1e-3, 2e-3, 1e-2, 2e-2])
def test_c_equals_numpy_to_1e_12_pps(h):
    """Measured: max |numpy - C| 2e-13 pps (2000 steps, four muscles)."""
    f = random_forces(0, (2000, 4), 20.0)
    g = np.array([4.0, 50.0, *G2_ARM])
    a = gto.simulate(f, h, g, HUMAN, backend="numpy")
    b = gto.simulate(f, h, g, HUMAN, backend="c")
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)


def test_c_streaming_with_changing_steps_equals_numpy():
    f = random_forces(1, (300, 2), 30.0)
    dts = np.random.default_rng(2).uniform(1.5e-3, 2.5e-3, 300)  # a jittered sample clock
    a = gto.make_tendon_organs(G2_ARM, HUMAN, 2e-3, f[0], backend="numpy")
    b = gto.make_tendon_organs(G2_ARM, HUMAN, 2e-3, f[0], backend="c")
    assert (a.backend, b.backend) == ("numpy", "c")
    for row, dt in zip(f[1:], dts[1:], strict=True):
        np.testing.assert_allclose(b.step(row, dt), a.step(row, dt), rtol=0, atol=1e-12)
    z, force, r = b.state_arrays()
    np.testing.assert_allclose(r, a.state.r_pps, rtol=0, atol=1e-12)
    np.testing.assert_allclose(z, a.state.z, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(force, a.state.force_N)


def test_c_bad_inputs_raise_like_numpy_and_change_nothing():
    organs = cgto.CTendonOrgans([4.0, 4.0], CAT, 1e-3, force_N=[1.0, 2.0])
    organs.step([3.0, 3.0])
    before = organs.state_arrays()
    bad_rows = ([np.nan, 1.0], [1.0, np.inf], [1.0, 2 * MAX_FORCE_N])
    for bad in bad_rows:
        with pytest.raises(ValueError, match="force_N"):
            organs.step(bad)
        with pytest.raises(ValueError, match="force_N"):  # atomic over a run
            organs.run(np.array([[5.0, 5.0], bad]))
        for x, y in zip(organs.state_arrays(), before, strict=True):
            np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="dt_s"):
        organs.step([1.0, 1.0], dt_s=0.5)
    with pytest.raises(ValueError, match="force_scale_N"):
        cgto.CTendonOrgans([4.0, -1.0], CAT)


def test_status_code_of_the_force_range_is_in_the_header():
    assert abi.header_status_codes()["PS_ERR_FORCE_RANGE"] == abi.Status.PS_ERR_FORCE_RANGE
    consts = abi.header_constants()
    assert consts["PS_GTO_MAX_FORCE_N"] == MAX_FORCE_N
    assert consts["PS_GTO_MAX_STEP_S"] == gto.MAX_STEP_S
    assert consts["PS_GTO_FX_FORCE_ONE"] == cgto.FX_FORCE
    assert consts["PS_GTO_FX_RATE_ONE"] == cgto.FX_RATE
    assert consts["PS_GTO_FX_INV_SCALE_ONE"] == cgto.FX_INV_SCALE


# -- fixed point -------------------------------------------------------------------------------
def brachialis_trace(h: float) -> np.ndarray:
    t = np.arange(0.0, 3.0, h)
    return 200 + 150 * np.sin(2 * np.pi * t) + (t > 1.5) * 100.0


def test_fixed_point_error_against_double():
    """HUMAN BRA (G2 = 179.5 N), 2 ms, a 50-350 N sinusoid with a 100 N step: measured
    0.00033 pps RMS, 0.00065 max; CAT (G2 = 4 N) on the same shape / 20: 0.0042 RMS, 0.020
    max (the Q8 force rounds to 4 mN, 0.06 pps at 15 pps/N)."""
    h = 2e-3
    f = brachialis_trace(h)
    d = gto.simulate(f, h, G2_ARM[0], HUMAN, backend="numpy")
    x = cgto.fixed_rates(f, h, G2_ARM[0], HUMAN)
    assert np.sqrt(np.mean((d - x) ** 2)) < 0.001 and np.max(np.abs(d - x)) < 0.002
    d = gto.simulate(f / 20, h, 4.0, CAT, backend="numpy")
    x = cgto.fixed_rates(f / 20, h, 4.0, CAT)
    assert np.sqrt(np.mean((d - x) ** 2)) < 0.01 and np.max(np.abs(d - x)) < 0.04


def test_fixed_point_against_the_reference():
    """The device form against the continuous system directly: a 20 ms rise 0-300 N on BRA at
    2 ms, measured 0.0004 pps RMS."""
    h = 2e-3
    t = np.arange(0.0, 2.0, h)

    def force(s: float) -> float:
        return 300.0 * min(max((s - 0.5) / 0.02, 0.0), 1.0)

    x = cgto.fixed_rates(np.array([force(s) for s in t]), h, G2_ARM[0], HUMAN)
    ref = reference_rates(force, t, G2_ARM[0], HUMAN)
    assert np.sqrt(np.mean((x - ref) ** 2)) < 0.002


def test_fixed_point_refuses_plans_it_cannot_bound():
    with pytest.raises(ValueError, match="PS_ERR_CONFIG"):
        cgto.fixed_plan(CAT.replace(den=(0.2, 4.0)), 1e-3)  # complex poles
    with pytest.raises(ValueError, match="PS_ERR_CONFIG"):
        cgto.fixed_plan(CAT.replace(gain_pps=5000.0), 1e-3)  # rates beyond Q16's int32
    x = cgto.fixed_rates(np.array([0.0, -3.0, 0.0]), 1e-3, 4.0, CAT)  # slack is 0
    np.testing.assert_array_equal(x, 0.0)
