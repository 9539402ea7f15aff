"""The tendon organ (Ib) step against an independent reference (scipy solve_ivp of the
transfer function in scipy's own realisation, and its closed-form step response), the
published constants, the input rules and the preset's force scales."""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from proprio_env.experiments.gto import CASES, rise
from spindle import tendon_organ as gto
from spindle.tendon_organ_params import (
    ARM26_MAX_ISOMETRIC_FORCE_N,
    CAT,
    HUMAN,
    MAX_FORCE_N,
    TendonOrganParams,
    force_scales_N,
    static_rate_pps,
    static_sensitivity_pps_per_N,
)
from spindle.tendon_organ_reference import reference_rates, step_response

OSIM = Path(__file__).resolve().parents[2] / "shared" / "reference" / "opensim" / "arm26.osim"


SINE = "sinusoid 5 +- 4 N, 2 Hz"
"""The experiment's force cases (steps with a 20 ms rise, a ramp, a sinusoid) are the
tests' inputs."""


@cache
def reference_on_1ms_grid(case: str) -> tuple[np.ndarray, np.ndarray]:
    """The reference of CASES[case] at every ms of 0-2 s (the 2 and 10 ms grids are every
    2nd and 10th of these times), solved once per case."""
    t = np.arange(2001) * 1e-3
    return t, reference_rates(CASES[case], t, CAT.force_scale_N, CAT)


def rms(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


# -- accuracy against the independent reference ---------------------------------------------
@pytest.mark.parametrize("h", [1e-3, 2e-3, 1e-2])
@pytest.mark.parametrize("case", list(CASES))
def test_step_within_0p1_pps_rms_of_the_continuous_system(case, h):
    """Measured (CAT, G2 = 4 N, 2 s): step up 0.0000/0.00001/0.008 pps RMS at 1/2/10 ms,
    step down ~0/~0/0.0023, ramp ~0/0.00005/0.0012, sinusoid 0.00035/0.0014/0.034."""
    t_ref, ref = reference_on_1ms_grid(case)
    stride = round(h / 1e-3)
    t = t_ref[::stride]
    f = np.array([CASES[case](x) for x in t])
    ib = gto.simulate(f, h, CAT.force_scale_N, CAT, backend="numpy")
    assert rms(ib, ref[::stride]) < 0.1
    assert np.all(ib >= 0) and np.all(np.isfinite(ib))


def test_step_at_20_ms_is_stable_and_close():
    """At the longest step the issue names (20 ms), measured: sinusoid 0.133 pps RMS, the
    20 ms rise 0.11 (the force is no longer a line between samples)."""
    t_ref, ref = reference_on_1ms_grid(SINE)
    t = t_ref[::20]
    f = np.array([CASES[SINE](x) for x in t])
    ib = gto.simulate(f, 0.02, CAT.force_scale_N, CAT, backend="numpy")
    assert rms(ib, ref[::20]) < 0.15


def test_force_step_from_rest_matches_the_closed_form():
    """A step between two samples is a line over that interval, centred half a step before
    the sample that first reads the new force: against the closed form of the ideal step at
    that centre, measured 0.011 pps RMS at h = 0.2 ms over 1.5 s."""
    h = 2e-4
    t = np.arange(0.0, 1.5 + h / 2, h)
    f = np.where(t < 0.5 - 1e-12, 2.0, 12.0)
    ib = gto.simulate(f, h, CAT.force_scale_N, CAT, backend="numpy")
    after = t >= 0.5 - 1e-12
    ref = step_response(t[after] - t[after][0] + h / 2, 2.0, 12.0, CAT.force_scale_N, CAT)
    assert rms(ib[after], ref) < 0.015
    assert ib[0] == pytest.approx(static_rate_pps(CAT, 2.0, CAT.force_scale_N), abs=1e-12)


def test_human_preset_on_brachialis_forces():
    """Human BRA scale (G2 = 179.5 N), a 0-400 N ramp-and-hold at 2 ms: measured 0.0001."""
    g2 = float(force_scales_N(HUMAN, ARM26_MAX_ISOMETRIC_FORCE_N["BRA"]))
    force = rise(0.2, 0.5, 0.0, 400.0)
    h = 2e-3
    t = np.arange(0.0, 2.0 + h / 2, h)
    ib = gto.simulate(np.array([force(x) for x in t]), h, g2, HUMAN, backend="numpy")
    assert rms(ib, reference_rates(force, t, g2, HUMAN)) < 0.01


# -- what the published model does ---------------------------------------------------------
def test_ramp_and_hold_overshoots_then_adapts_to_the_static_log():
    """Lin & Crago's GTO: dynamic overshoot during the ramp (H(inf) = 1.7 > H(0) = 1), slow
    adaptation (poles at 0.2 and 2 s^-1) to G1 ln(F/G2 + 1) in the hold."""
    h = 2e-3
    t = np.arange(0.0, 20.0 + h / 2, h)
    force = rise(1.0, 0.5, 0.0, 10.0)
    ib = gto.simulate(np.array([force(x) for x in t]), h, CAT.force_scale_N, CAT,
                      backend="numpy")
    static = float(static_rate_pps(CAT, 10.0, CAT.force_scale_N))
    assert static == pytest.approx(60.0 * np.log(3.5))
    assert ib[t <= 1.0].max() == 0.0
    assert ib.max() > 1.05 * static  # overshoot
    assert t[np.argmax(ib)] < 1.6  # at the end of the ramp, not in the hold
    # the slow pole (0.2 s^-1) leaves 0.3 % of the adaptation after 18.5 s of hold (measured
    # 75.40 against 75.17 pps), approached from above and still falling
    tail = ib[t >= 15.0]
    assert 0 < tail[-1] - static < 0.005 * static
    assert np.all(np.diff(tail) < 0)


def test_static_sensitivity_in_pps_per_newton():
    """dIb/dF at rest = G1 / (G2 + F): 15 pps/N at 0 N for the cat (60 / 4)."""
    assert static_sensitivity_pps_per_N(CAT, 0.0, 4.0) == pytest.approx(15.0)
    g2 = force_scales_N(HUMAN, [ARM26_MAX_ISOMETRIC_FORCE_N[m] for m in ("BRA", "TRImed")])
    np.testing.assert_allclose(g2, [4.0 * 987.26 / 22.0, 4.0 * 624.3 / 22.0])
    s = static_sensitivity_pps_per_N(HUMAN, 0.0, g2)
    np.testing.assert_allclose(s, 40.0 / g2)
    # finite-difference of the simulated static rates agrees with the formula
    h = 1e-3
    rates = [gto.simulate(np.full(5, f), h, g2[0], HUMAN, backend="numpy")[-1]
             for f in (99.0, 101.0)]
    assert (rates[1] - rates[0]) / 2.0 == pytest.approx(
        float(static_sensitivity_pps_per_N(HUMAN, 100.0, g2[0])), rel=1e-4)


def test_arm26_max_isometric_forces_are_the_osim_files():
    if not OSIM.exists():
        pytest.skip(f"{OSIM} not present")
    text = OSIM.read_text()
    for muscle, value in ARM26_MAX_ISOMETRIC_FORCE_N.items():
        block = re.search(rf'<Thelen2003Muscle name="{muscle}">(.*?)</Thelen2003Muscle>',
                          text, re.S).group(1)
        osim = float(re.search(r"<max_isometric_force>([^<]+)<", block).group(1))
        assert value == pytest.approx(osim, abs=1e-9)


def test_transfer_function_decodes_myogens_bilinear_coefficients():
    """myogen's _gto.pyx difference equation (den = 0.4 T^2 + 4.4 T + 4, b0 = (0.4 T^2 +
    5.16 T + 6.8)/den, ...) is the bilinear transform of CAT's H(s); the OpenSim plugin's
    numerator (68, 103.2, 16) is 40 x CAT.num."""
    T = 1e-3
    b2, b1, b0 = CAT.num
    a1, a0 = CAT.den
    k = 2.0 / T
    num_z = [b2 * k**2 + b1 * k + b0, 2 * b0 - 2 * b2 * k**2, b2 * k**2 - b1 * k + b0]
    den_z = [k**2 + a1 * k + a0, 2 * a0 - 2 * k**2, k**2 - a1 * k + a0]
    den = 0.4 * T**2 + 4.4 * T + 4
    myogen_b = [(0.4 * T**2 + 5.16 * T + 6.8) / den, (0.8 * T**2 - 13.6) / den,
                (0.4 * T**2 - 5.16 * T + 6.8) / den]
    myogen_a = [(0.8 * T**2 - 8) / den, (0.4 * T**2 - 4.4 * T + 4) / den]
    np.testing.assert_allclose(np.array(num_z) / den_z[0], myogen_b, rtol=1e-12)
    np.testing.assert_allclose(np.array(den_z[1:]) / den_z[0], myogen_a, rtol=1e-12)
    np.testing.assert_allclose(np.array(CAT.num) * 40, [68.0, 103.2, 16.0], rtol=1e-12)
    assert CAT.dc_gain == pytest.approx(1.0)


def test_exact_discretisation_matches_an_eigen_decomposition():
    """Phi = e^{Ah} from the Taylor scaling-and-squaring equals V e^{Lh} V^-1 (distinct real
    poles -100, -2, -0.2 s^-1), to 1e-13 at 1, 10 and 100 ms."""
    A, _, _ = gto.state_space(CAT)
    lam, V = np.linalg.eig(A)
    for h in (1e-3, 1e-2, 0.1):
        ref = np.real(V @ np.diag(np.exp(lam * h)) @ np.linalg.inv(V))
        np.testing.assert_allclose(gto.plan(CAT, h).phi, ref, atol=1e-13)


# -- input rules -----------------------------------------------------------------------------
def test_bad_inputs_raise_and_leave_the_state_as_it_was():
    organs = gto.TendonOrgans([4.0, 4.0], CAT, 1e-3, force_N=[1.0, 2.0])
    organs.step([3.0, 3.0])
    before = organs.state.copy()
    for bad in ([np.nan, 1.0], [1.0, np.inf], [1.0, 2 * MAX_FORCE_N], [1.0, 2.0, 3.0]):
        with pytest.raises(ValueError, match="force_N"):
            organs.step(bad)
        np.testing.assert_array_equal(organs.state.z, before.z)
        np.testing.assert_array_equal(organs.state.r_pps, before.r_pps)
    for bad in (0.0, -1e-3, np.nan, 0.5):
        with pytest.raises(ValueError, match="dt_s"):
            organs.step([1.0, 1.0], dt_s=bad)
    with pytest.raises(TypeError, match="dt_s"):
        organs.step([1.0, 1.0], dt_s="1ms")
    with pytest.raises(ValueError, match="force_scale_N"):
        gto.TendonOrgans([4.0, 0.0], CAT)
    with pytest.raises(ValueError, match="gain_pps"):
        TendonOrganParams(gain_pps=-1.0)
    with pytest.raises(ValueError, match="den"):
        TendonOrganParams(den=(-2.2, 0.4))


def test_negative_force_is_a_slack_tendon():
    organs = gto.TendonOrgans(4.0, CAT, 1e-3, force_N=5.0)
    ref = gto.TendonOrgans(4.0, CAT, 1e-3, force_N=5.0)
    for _ in range(50):
        a = organs.step(-3.0)
        b = ref.step(0.0)
    np.testing.assert_array_equal(a, b)
    assert gto.count_negative([-3.0, 0.0, 2.0, -1e-9]) == 2


def test_rates_never_negative_or_non_finite_on_random_forces():
    """Random forces 0..MAX_FORCE_N with sudden drops (the undershoot of H would go below 0)."""
    rng = np.random.default_rng(0)
    f = rng.uniform(0, 1, (2000, 16)) ** 8 * MAX_FORCE_N
    f[::97] = 0.0
    for h in (1e-3, 2e-2):
        ib = gto.simulate(f, h, np.full(16, 4.0), CAT, backend="numpy")
        assert np.all(np.isfinite(ib)) and ib.min() == 0.0


def test_streaming_equals_simulate_and_vectorises_over_muscles():
    rng = np.random.default_rng(1)
    f = np.cumsum(rng.normal(0, 1, (300, 3)), axis=0) ** 2
    g2 = np.array([4.0, 50.0, 179.5])
    batch = gto.simulate(f, 1e-3, g2, HUMAN, backend="numpy")
    for i in range(3):
        one = gto.simulate(f[:, i], 1e-3, g2[i], HUMAN, backend="numpy")
        np.testing.assert_allclose(batch[:, i], one, rtol=0, atol=1e-12)
    organs = gto.TendonOrgans(g2, HUMAN, 1e-3, force_N=f[0])
    rows = [organs.rate_pps()] + [organs.step(row) for row in f[1:]]
    np.testing.assert_array_equal(np.array(rows), batch)


@pytest.mark.slow
def test_experiment_writes_its_figures_and_numbers(tmp_path):
    from proprio_env.experiments import gto as experiment

    numbers = experiment.run(tmp_path, quick=True)
    for name in ("ramp_hold", "static", "accuracy", "implementations"):
        assert (tmp_path / f"gto_{name}.png").stat().st_size > 1000
    assert max(v for row in numbers.accuracy_pps.values() for v in row[:4]) < 0.1
    assert numbers.opensim_over_ours == pytest.approx(40.0, rel=1e-3)
    assert numbers.overshoot_ratio > 1.3
    assert "pps/N" in numbers.summary_md()
