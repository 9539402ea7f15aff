"""The theta-method against the independent stiff reference (scipy Radau, rtol 1e-10).

The reference integrates the published (T, dT/dt) form with the M*d2L/dt2 term, so these
tests also check the (T, v) reformulation of the core.
"""

import numpy as np
import pytest

import spindle
from spindle.reference import Stimulus, ramp_and_hold, solve_reference

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


def fig3_rates(speed, gd, gs, hold_s=0.6):
    """The reference (Table 1, cat) on one Fig. 3 run, cut short 0.6 s into the hold; the
    (rest, ramp, late hold) samples' rates."""
    end = 1.0 + 0.13 / speed
    stim, t, _, _ = protocol(speed, gd, gs, dt=2e-3, duration=round((end + hold_s) / 2e-3) * 2e-3)
    ref = solve_reference(stim, t)
    parts = {"rest": t < 1.0, "ramp": (t >= 1.0) & (t <= end), "hold": t > end + hold_s - 0.1}
    return {k: (ref.ia[m], ref.ii[m]) for k, m in parts.items()}


@pytest.fixture(scope="module")
def fig3_runs():
    return {(speed, gd, gs): fig3_rates(speed, gd, gs)
            for speed, gd, gs in ((1.55, 0.0, 0.0), (1.55, 70.0, 0.0), (1.55, 0.0, 70.0),
                                  (0.11, 0.0, 0.0))}


def test_reference_reproduces_the_published_fig3_qualities(fig3_runs):
    """The spec's account of Mileusnic (2006) Fig. 3 (cat, 0.95 -> 1.08 L0), each statement as a
    number (measured here: rest Ia 0.00 / 27.8 / 64.8 pps without drive / dynamic / static;
    hold Ia 42-47 pps without drive; peak Ia 205 pps without drive and 333 pps with dynamic
    drive at 1.55 L0/s; II's ramp overshoot 1.1x its length response, Ia's 3.9x)."""
    plain, dynamic, static = (fig3_runs[(1.55, *d)] for d in ((0, 0), (70, 0), (0, 70)))
    slow = fig3_runs[(0.11, 0.0, 0.0)]
    # "without fusimotor drive, Ia sits near 0 before the stretch, rises during the ramp and
    # settles at tens of pps on the hold"
    for run in (plain, slow):
        ia_rest, ia_ramp, ia_hold = (run[k][0] for k in ("rest", "ramp", "hold"))
        assert ia_rest.max() < 1.0
        assert ia_ramp.max() > ia_hold.mean()
        assert 10.0 <= ia_hold.min() and ia_hold.max() < 100.0
    # "dynamic drive (70 pps) gives a large overshoot during fast ramps": above twice the hold,
    # and at least 100 pps above the undriven ramp's peak
    assert dynamic["ramp"][0].max() > 2 * dynamic["hold"][0].mean()
    assert dynamic["ramp"][0].max() > plain["ramp"][0].max() + 100.0
    # "static drive raises the background rate": tens of pps more Ia and II at rest
    assert static["rest"][0].min() > plain["rest"][0].max() + 10.0
    assert static["rest"][1].min() > plain["rest"][1].max() + 10.0
    # "II follows length with little velocity sensitivity": its ramp overshoot over the hold,
    # relative to its length response, is under half of Ia's
    def dynamic_index(run, afferent):
        rest, ramp, hold = (run[k][afferent] for k in ("rest", "ramp", "hold"))
        return (ramp.max() - hold.mean()) / (hold.mean() - rest.mean())

    assert dynamic_index(plain, 1) < 0.5 * dynamic_index(plain, 0)
    # and a 14x faster ramp raises the Ia peak more than the II peak
    assert plain["ramp"][0].max() / slow["ramp"][0].max() > \
        plain["ramp"][1].max() / slow["ramp"][1].max()


def test_reference_smoothing_changes_nothing():
    # onset 1.0014 s: the rest hold that failed at every eps before the one-sided segment rule
    stim = ramp_and_hold(speed_L0_s=1.55, ramp_start_s=1.0014, duration_s=1.25)
    t = np.arange(1251) * 1e-3
    a = solve_reference(stim, t, eps_L0_s=1e-7)
    b = solve_reference(stim, t, eps_L0_s=1e-9)  # the smoothing's effect falls as eps^2
    # far below the 0.32 pps the reference checks at 1 ms, and the ~3e-3 pps at 0.1 ms
    assert np.abs(a.ia - b.ia).max() < 1e-4
    assert np.abs(a.ii - b.ii).max() < 1e-4


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


# --- Any onset, any drive ------------------------------------------------
# Radau's last stage sits exactly on a segment's end, where a piecewise velocity already takes
# the next piece's value; the reference failed ("Required step size is less than spacing
# between numbers") in the rest hold of ramps whose onset happened to make that stage bite.

FINE_DT_S = 1e-4
# The trapezoidal rule at 0.1 ms, fed the exact lengths every 0.1 ms, is ~100x more accurate than
# at the 1 ms default (second order; 0.32 pps RMS worst run at 1 ms in docs/spindle_accuracy.md):
# measured <= 5.3e-3 pps RMS, 0.033 pps max over the slow sweep below (216 runs, 0.3 s holds).
# Both tolerances are ~30x below the 1 ms figure the reference is used to check, and 2-3x above
# what the core reaches.
FINE_RMS_PPS, FINE_MAX_PPS = 0.01, 0.1
START_L0, END_L0 = 0.95, 1.08


def issue_stimulus(speed, onset, gd, gs, duration, left_continuous=False):
    """The failing ramp, written as a user would (closed-open velocity by default)."""
    off = onset + (END_L0 - START_L0) / speed
    if left_continuous:
        def velocity(t):
            return speed if onset < t <= off else 0.0
    else:
        def velocity(t):
            return speed if onset <= t < off else 0.0
    return Stimulus(lambda t: min(max(START_L0 + speed * (t - onset), START_L0), END_L0),
                    velocity, lambda t: 0.0, duration, (onset, off), gd, gs)


def check_against_the_core_and_rest(stim, onset):
    """The reference on a 0.1 ms grid: the initial hold at the equilibrium rates, and the whole
    run within FINE_* of the trapezoidal core stepped at 0.1 ms. Returns the (RMS, max abs)
    errors of Ia and II."""
    t = np.arange(int(stim.duration_s / FINE_DT_S) + 1) * FINE_DT_S
    t = t[t <= stim.duration_s]
    ref = solve_reference(stim, t)
    gd, gs = stim.gamma_dyn_pps, stim.gamma_stat_pps
    ia_rest, ii_rest = spindle.afferents(spindle.equilibrium_state(START_L0, gd, gs))
    before = t < onset
    np.testing.assert_allclose(ref.ia[before], ia_rest[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(ref.ii[before], ii_rest[0], rtol=0, atol=1e-6)
    length = np.array([stim.length_L0(x) for x in t])
    core = spindle.simulate(length, FINE_DT_S, gamma_dyn=gd, gamma_stat=gs, step=FINE_DT_S)
    errors = []
    for ours, theirs in ((ref.ia, core.ia), (ref.ii, core.ii)):
        errors += [rms(ours, theirs), float(np.abs(ours - theirs).max())]
        assert errors[-2] <= FINE_RMS_PPS
        assert errors[-1] <= FINE_MAX_PPS
    return tuple(errors)


@pytest.mark.parametrize(("speed", "onset", "gd", "gs"), [
    (1.55, 1.0014, 0.0, 0.0),   # the two rest holds that used to fail
    (0.66, 1.0053, 70.0, 0.0),
])
def test_reference_solves_the_issue_13_ramps(speed, onset, gd, gs):
    off = onset + (END_L0 - START_L0) / speed
    check_against_the_core_and_rest(issue_stimulus(speed, onset, gd, gs, off + 0.15), onset)


def test_reference_takes_either_one_sided_velocity_convention_at_the_corners():
    onset, speed = 1.0014, 1.55
    off = onset + (END_L0 - START_L0) / speed
    check_against_the_core_and_rest(
        issue_stimulus(speed, onset, 0.0, 70.0, off + 0.15, left_continuous=True), onset)


def test_reference_holds_rest_across_breakpoints_at_any_time():
    onsets = (0.9, 1.0, 1.0014, 1.0053, 1.0891)
    stim = Stimulus(lambda t: 0.95, lambda t: 0.0, lambda t: 0.0, 1.2, onsets, 300.0, 70.0)
    t = np.linspace(0.0, 1.2, 241)
    ref = solve_reference(stim, t)
    ia_rest, ii_rest = spindle.afferents(spindle.equilibrium_state(0.95, 300.0, 70.0))
    np.testing.assert_allclose(ref.ia, ia_rest[0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(ref.ii, ii_rest[0], rtol=0, atol=1e-6)


SWEEP_ONSETS_S = (0.9, 0.9371, 0.96, 0.9833, 1.0, 1.0014, 1.0053, 1.0207, 1.05, 1.0629, 1.0891,
                  1.1)
SWEEP_DRIVES_PPS = [(gd, gs) for gd in (0.0, 70.0, 300.0) for gs in (0.0, 70.0)]


@pytest.mark.slow
@pytest.mark.parametrize("speed", SPEEDS)
@pytest.mark.parametrize(("gd", "gs"), SWEEP_DRIVES_PPS)
@pytest.mark.parametrize("onset", SWEEP_ONSETS_S)
def test_reference_solves_every_onset_drive_and_speed(onset, gd, gs, speed):
    stim = ramp_and_hold(START_L0, END_L0, speed, onset,
                         onset + (END_L0 - START_L0) / speed + 0.3, gd, gs)
    check_against_the_core_and_rest(stim, onset)
