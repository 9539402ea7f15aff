"""The theta-method against the independent stiff reference (scipy Radau, rtol 1e-10).

The reference integrates the published (T, dT/dt) form with the M*d2L/dt2 term, so these
tests also check the (T, v) reformulation of the core.
"""

import numpy as np
import pytest

import spindle
from spindle.reference import ramp_and_hold, solve_reference

pytest.importorskip("scipy")

DRIVES = [(0.0, 0.0), (70.0, 0.0), (0.0, 70.0)]
SPEEDS = [0.11, 0.66, 1.55]


def protocol(speed, gd, gs, dt=1e-3, duration=3.3):
    stim = ramp_and_hold(speed_L0_s=speed, gamma_dyn_pps=gd, gamma_stat_pps=gs,
                         duration_s=duration)
    t = np.arange(0, duration + dt / 2, dt)
    length = np.array([stim.length_L0(x) for x in t])
    velocity = np.array([stim.velocity_L0_s(x) for x in t])
    return stim, t, length, velocity


def rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)))


@pytest.fixture(scope="module")
def fast_ramp_reference():
    stim, t, length, velocity = protocol(1.55, 70.0, 0.0, duration=1.6)
    return t, length, velocity, solve_reference(stim, t)


def test_reference_reproduces_the_published_fig3_qualities(fast_ramp_reference):
    t, _, _, ref = fast_ramp_reference
    before = t < 1.0
    # the 70 pps dynamic drive: strong overshoot at the end of the fast ramp
    assert ref.ia.max() > 2 * ref.ia[-1] > 0
    assert ref.ia[before].std() < 1e-6  # at rest before the stretch


def test_reference_smoothing_changes_nothing():
    stim, t, _, _ = protocol(1.55, 0.0, 0.0, duration=1.5)
    a = solve_reference(stim, t, eps_L0_s=1e-7)
    b = solve_reference(stim, t, eps_L0_s=1e-6)
    assert np.abs(a.ia - b.ia).max() < 1e-3
    assert np.abs(a.ii - b.ii).max() < 1e-3


def test_default_method_at_1ms_meets_half_a_pps_on_a_fast_dynamic_ramp(fast_ramp_reference):
    _, length, _, ref = fast_ramp_reference
    r = spindle.simulate(length, 1e-3, gamma_dyn=70.0)
    assert r.method == "trapezoidal" and r.step_s == pytest.approx(1e-3)
    assert rms(r.ia, ref.ia) <= 0.5
    assert rms(r.ii, ref.ii) <= 0.5


@pytest.mark.parametrize(("method", "step_s", "tol_pps"), [
    ("trapezoidal", 1e-3, 0.5),
    ("backward_euler", 0.1e-3, 1.0),
    ("forward_euler", 20e-6, 1.5),
])
def test_each_method_meets_its_documented_tolerance(fast_ramp_reference, method, step_s,
                                                    tol_pps):
    _, length, velocity, ref = fast_ramp_reference
    r = spindle.simulate(length, 1e-3, velocity=velocity, gamma_dyn=70.0, method=method,
                         step=step_s)
    assert rms(r.ia, ref.ia) <= tol_pps
    assert rms(r.ii, ref.ii) <= tol_pps


def test_forward_euler_converges_to_the_reference_at_first_order():
    stim, t, length, velocity = protocol(0.66, 0.0, 0.0, dt=2e-3, duration=1.4)
    ref = solve_reference(stim, t)
    errors = []
    steps = [200e-6, 100e-6, 50e-6]
    for h in steps:
        r = spindle.simulate(length, 2e-3, velocity=velocity, method="forward_euler", step=h)
        errors.append(rms(r.ia, ref.ia))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    # first order: halving the step about halves the error (second order would quarter it)
    assert np.all((orders > 0.7) & (orders < 1.3)), (errors, orders)


def test_trapezoidal_rule_converges_faster_than_first_order():
    stim, t, length, velocity = protocol(0.66, 0.0, 70.0, dt=2e-3, duration=1.4)
    ref = solve_reference(stim, t)
    e_coarse = rms(spindle.simulate(length, 2e-3, velocity=velocity, gamma_stat=70.0,
                                    step=2e-3).ia, ref.ia)
    e_fine = rms(spindle.simulate(length, 2e-3, velocity=velocity, gamma_stat=70.0,
                                  step=0.5e-3).ia, ref.ia)
    assert e_fine < e_coarse / 4


@pytest.mark.slow
@pytest.mark.parametrize(("gd", "gs"), DRIVES)
@pytest.mark.parametrize("speed", SPEEDS)
def test_default_method_meets_the_target_on_every_fig3_run(speed, gd, gs):
    stim, t, length, _ = protocol(speed, gd, gs)
    ref = solve_reference(stim, t)
    r = spindle.simulate(length, 1e-3, gamma_dyn=gd, gamma_stat=gs)
    assert rms(r.ia, ref.ia) <= 0.5
    assert rms(r.ii, ref.ii) <= 0.5
