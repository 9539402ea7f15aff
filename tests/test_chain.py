"""The processing chain: sensor, filters, fusimotor model, streaming and batch paths, bad input."""

import math

import numpy as np
import pytest

import spindle
from proprio_env.body.encoder import Encoder
from spindle.chain import COUNTERS, ArmChain, ChainConfig, make_chain, resolve_backend, run_chain
from spindle.chain.conditioning import difference, track, tracking_step
from spindle.chain.config import MAX_SLEW_LIMIT_L0_S
from spindle.chain.fusimotor import (
    SEED_PAPER,
    FusimotorParams,
    MotionPredictor,
    gamma_dynamic_pps,
    gamma_static_pps,
)
from spindle.chain.sensor import AX12, INVALID_READING, Calibration, MedianFilter, median_filter

scipy_ndimage = pytest.importorskip("scipy.ndimage")
scipy_signal = pytest.importorskip("scipy.signal")


def motion(duration_s=2.0, seed=0, dt=1e-3):
    """A 130 deg/s flexion-extension and its encoder readings."""
    t = np.arange(0.0, duration_s, dt)
    period = 2 * 90 / 130.0
    angle = 20 + 90 * (1 - np.abs(2 * ((t % period) / period) - 1))
    t_s, counts = Encoder(rng=seed).record(t, angle)
    return t, angle, t_s, counts


# -- sensor ------------------------------------------------------------------------------
def test_median_filter_equals_scipy_on_random_data():
    rng = np.random.default_rng(1)
    x = rng.integers(0, 1024, size=5000).astype(float)
    # origin=3 puts the 7-sample window at x[k-6 .. k]; mode="nearest" pads with x[0]
    ref = scipy_ndimage.median_filter(x, size=7, mode="nearest", origin=3)
    np.testing.assert_array_equal(median_filter(x, 7), ref)
    stream = MedianFilter(7)  # one signal, pushed one sample at a time and in blocks
    stream.reset(x[:1])
    pushed = [stream.push(x[None, i:i + 1])[0, 0] for i in range(1, 2000)]
    pushed += list(stream.push(x[None, 2000:])[0])
    np.testing.assert_array_equal(pushed, ref[1:])


def test_median_filter_removes_isolated_spikes():
    x = np.full(200, 400.0)
    x[50] = 65000.0
    x[120:123] = 0.0  # three in a row: still fewer than half the window
    np.testing.assert_array_equal(median_filter(x), 400.0)


def test_encoder_readings_are_quantised_calibrated_and_at_500_hz():
    t = np.arange(0, 4.0, 1e-3)
    angle = 65 + 40 * np.sin(2 * np.pi * 0.5 * t)
    enc = Encoder(AX12.ideal(), rng=3)
    t_s, counts = enc.record(t, angle)
    assert counts.dtype == np.int64 and counts.min() >= 0 and counts.max() <= 1023
    np.testing.assert_allclose(np.diff(t_s), 1 / 500)
    cal = Calibration()
    # the ideal device is off by at most half a count
    err = cal.angle_deg(counts) - np.interp(t_s, t, angle)
    assert np.abs(err).max() <= 0.5 * AX12.deg_per_count + 1e-9
    assert cal.angle_deg(cal.counts(37.0)) == pytest.approx(37.0)
    assert cal.counts(0.0) == pytest.approx(290.4, abs=0.1)
    assert cal.counts(130.0) == pytest.approx(733.6, abs=0.1)
    assert Calibration(sign=-1).angle_deg(Calibration(sign=-1).counts(20.0)) == pytest.approx(20)


def test_encoder_noise_jitter_and_invalid_readings_follow_their_parameters():
    enc = Encoder(rng=7)
    t = np.array([0.0, 200.0])
    t_s, counts = enc.record(t, np.array([65.0, 65.0]))
    intervals = np.diff(t_s)
    assert intervals.mean() == pytest.approx(2e-3, rel=1e-3)
    assert intervals.std() == pytest.approx(AX12.jitter_s, rel=0.05)  # per interval
    valid = (counts >= 0) & (counts <= 1023)
    bad_rate = 1 - valid.mean()
    # half of the invalid readings are dropouts, about 98 % of the corrupt words are out of range
    assert bad_rate == pytest.approx(AX12.invalid_rate * (0.5 + 0.5 * 64512 / 65536), rel=0.15)
    assert (counts == INVALID_READING).mean() == pytest.approx(AX12.invalid_rate / 2, rel=0.2)
    good = counts[valid & (np.abs(counts - 512) < 10)]
    # rounding N(0, 0.6) noise: the standard deviation of the counts is sqrt(0.36 + 1/12)
    assert good.std() == pytest.approx(math.sqrt(0.36 + 1 / 12), rel=0.05)


# -- length conditioning ---------------------------------------------------------------------
def test_tracking_filter_step_equals_a_tight_ode_solution():
    from scipy.integrate import solve_ivp

    w = 2 * np.pi * 10
    rng = np.random.default_rng(0)
    for dt in rng.uniform(1e-4, 0.05, size=8):
        x, v, u0, u1 = rng.normal(size=4)

        def rhs(t, y, u0=u0, u1=u1, dt=dt):
            u = u0 + (u1 - u0) * t / dt  # first-order hold
            return [y[1], w * w * (u - y[0]) - 2 * w * y[1]]

        ref = solve_ivp(rhs, (0, dt), [x, v], method="DOP853", rtol=1e-12, atol=1e-13).y[:, -1]
        x1, v1, a1 = tracking_step(x, v, u0, u1, dt, w)
        np.testing.assert_allclose([x1, v1], ref, rtol=1e-8, atol=1e-10)
        assert a1 == pytest.approx(w * w * (u1 - x1) - 2 * w * v1)


def test_tracking_filter_follows_a_ramp_with_its_documented_lag():
    t = np.cumsum(np.full(500, 2e-3)) + np.random.default_rng(2).uniform(-2e-4, 2e-4, 500)
    u = 0.9 + 0.5 * t
    x, v, a = track(t, u, natural_hz=10.0)
    late = t > 0.6
    np.testing.assert_allclose(v[late], 0.5, rtol=1e-9)  # jittered samples change nothing
    np.testing.assert_allclose(a[late], 0.0, atol=1e-6)
    np.testing.assert_allclose((u[late] - x[late]) / 0.5, 2 / (2 * np.pi * 10), rtol=1e-9)


def test_filtering_cuts_the_noise_that_differencing_amplifies():
    rng = np.random.default_rng(5)
    t = np.arange(0, 2.0, 2e-3)
    noisy = 1.0 + 0.002 * rng.normal(size=t.size)
    v_raw, _ = difference(t, noisy)
    _, v_filt, _ = track(t, noisy, 10.0)
    # white noise of sigma s differenced at dt: sigma_v = sqrt(2) s / dt = 1.41 L0/s
    assert v_raw[5:].std() == pytest.approx(math.sqrt(2) * 0.002 / 2e-3, rel=0.1)
    assert v_filt[100:].std() < 0.1 * v_raw[5:].std()


# -- fusimotor -------------------------------------------------------------------------------
def test_gamma_static_follows_h_exactly_and_clips_overshoot():
    L = np.linspace(0.5, 1.2, 71)
    lo, hi = 0.6, 1.1
    expected = np.clip(20 + 130 * (hi - L) / (hi - lo), 20, 150)
    np.testing.assert_allclose(gamma_static_pps(L, lo, hi), expected, rtol=0, atol=1e-12)
    assert gamma_static_pps(lo, lo, hi) == 150 and gamma_static_pps(hi, lo, hi) == 20
    with pytest.raises(ValueError, match="must exceed"):
        gamma_static_pps(1.0, 1.1, 1.0)


def test_gamma_dynamic_follows_g_exactly():
    now = np.array([1.0, 1.0, 1.0, 1.0])
    delayed = np.array([1.0 + 0.0021, 1.0 + 0.0019, 1.0, 0.9])  # shortening, slow, static, long
    np.testing.assert_array_equal(gamma_dynamic_pps(now, delayed), [0, 100, 100, 100])


def test_chain_gammas_follow_their_formulas_on_a_constructed_trace():
    t = np.arange(0, 3.0, 2e-3)
    angle = np.interp(t, [0, 0.5, 1.2, 2.0, 2.6, 3.0], [30, 30, 110, 110, 40, 40])
    trace = run_chain(t, angle_deg=angle)
    chain = ArmChain()
    expected_gs = gamma_static_pps(trace.template_L0, chain.length_min_L0, chain.length_max_L0)
    np.testing.assert_array_equal(trace.gamma_static_pps, expected_gs)
    # g(x): template(t - delay) from the trace itself (piecewise linear, sampled every 2 ms)
    delayed = np.stack([np.interp(t - SEED_PAPER.delay_s, t, trace.template_L0[:, k])
                        for k in range(2)], axis=-1)
    fall = delayed - trace.template_L0
    decided = np.abs(fall - SEED_PAPER.shortening_threshold_L0) > 1e-4  # not at the edge
    expected_gd = np.where(fall > SEED_PAPER.shortening_threshold_L0, 0.0, 100.0)
    np.testing.assert_array_equal(trace.gamma_dynamic_pps[decided], expected_gd[decided])
    # flexion (0.5-1.2 s) shortens BRA and lengthens TRImed, extension the reverse
    flexing = (t > 0.7) & (t < 1.1)
    extending = (t > 2.2) & (t < 2.5)
    assert np.all(trace.gamma_dynamic_pps[flexing] == [0, 100])
    assert np.all(trace.gamma_dynamic_pps[extending] == [100, 0])
    assert np.all(trace.gamma_dynamic_pps[(t > 1.6) & (t < 1.9)] == 100)  # static


def predictor_step_response(params, t_end=2.0, dt=1e-3, size=0.1):
    pred = MotionPredictor(params, n=1, n_muscles=1)
    pred.reset(np.zeros(1), np.array([[1.0]]))
    t = np.arange(dt, t_end, dt)
    out = np.array([pred.update(np.array([[ti]]), np.array([[[1.0 + size]]]))[0][0, 0, 0]
                    for ti in t])
    return t, out


def test_pi_predictor_overshoots_a_step_and_settles_as_its_loop_predicts():
    t, out = predictor_step_response(SEED_PAPER)
    overshoot = (out.max() - 1.1) / 0.1
    # the continuous loop (kp s + ki)/(s^2 + kp s + ki); the 50 Hz discrete loop is close to it
    kp, ki = SEED_PAPER.predictor_kp_1_s, SEED_PAPER.predictor_ki_1_s2
    _, yc = scipy_signal.step(([kp, ki], [1, kp, ki]), T=np.linspace(0, 2, 4001))
    assert overshoot > 0.2
    assert overshoot == pytest.approx(yc.max() - 1, abs=0.06)
    assert abs(out[t > 1.2] - 1.1).max() < 0.002  # settled within 2 % of the step
    # and exactly the discrete loop at its update instants: its transfer function from the
    # input to the template is ((a+b) z - a) / (z^2 - (2-a-b) z + (1-a)), a = kp dt, b = ki dt^2
    dt = SEED_PAPER.predictor_period_s
    a, b = kp * dt, ki * dt * dt
    n = 90
    step = np.r_[0.0, np.full(n - 1, 0.1)]  # the step reaches the loop at its first update
    y = scipy_signal.lfilter([0, a + b, -a], [1, -(2 - a - b), 1 - a], step)
    at_updates = np.interp(np.arange(1, n) * dt, t, out) - 1.0
    np.testing.assert_allclose(at_updates, y[1:], atol=1e-9)


def test_predictor_refuses_unstable_gains():
    with pytest.raises(ValueError, match="not stable"):
        FusimotorParams(predictor_kp_1_s=150.0)
    with pytest.raises(ValueError, match=r"delay_s=-1\.0 must be a finite real number >= 0"):
        FusimotorParams(delay_s=-1.0)


def test_intended_motion_switch_drives_the_template():
    t = np.arange(0, 1.5, 2e-3)
    still = np.full(t.size, 60.0)
    intended = np.interp(t, [0, 0.2, 0.9, 1.5], [60, 60, 100, 100])
    measured = run_chain(t, angle_deg=still)
    switched = run_chain(t, angle_deg=still, intended_angle_deg=intended)
    np.testing.assert_array_equal(measured.length_L0, switched.length_L0)  # same arm
    assert np.ptp(measured.template_L0[:, 0]) < 1e-12
    L_target = spindle.load_length_fits().length_L0(np.radians(100.0))
    np.testing.assert_allclose(switched.template_L0[-1], L_target, atol=2e-3)
    # the intended flexion shortens BRA: its gamma_d drops and its II moves although the
    # arm does not
    assert (switched.gamma_dynamic_pps[(t > 0.4) & (t < 0.8), 0] == 0).all()
    assert np.abs(switched.ii_pps - measured.ii_pps).max() > 1.0


# -- the chain -----------------------------------------------------------------------------
def test_streaming_and_batch_paths_are_identical():
    _, _, t_s, counts = motion(1.5)
    trace = run_chain(t_s, counts=counts, config=ChainConfig(backend="numpy"))
    chain = ArmChain()
    first = int(np.argmax((counts >= 0) & (counts <= 1023)))
    chain.reset(float(Calibration().angle_deg(counts[first])), t_s[first])
    samples = [chain.push_counts(t, c) for t, c in zip(t_s[first + 1:], counts[first + 1:],
                                                        strict=True)]
    for name in ("ia_pps", "ii_pps", "gamma_static_pps", "gamma_dynamic_pps", "length_L0",
                 "angle_deg", "template_L0"):
        np.testing.assert_array_equal(np.array([getattr(s, name) for s in samples]),
                                      getattr(trace, name)[first + 1:], err_msg=name)
    assert chain.counters == trace.counters


def test_chain_spindles_equal_simulate_on_the_chain_lengths():
    # the chain's sub-stepping is spindle.simulate's: same Hermite curve, same held drive
    t = np.arange(0, 1.0, 2e-3)
    angle = 40 + 30 * np.sin(2 * np.pi * 1.3 * t)
    trace = run_chain(t, angle_deg=angle)
    for k in range(2):
        ref = spindle.simulate(trace.length_L0[:, k], 2e-3, velocity=trace.velocity_L0_s[:, k],
                               gamma_dyn=trace.gamma_dynamic_pps[:, k],
                               gamma_stat=trace.gamma_static_pps[:, k], params=spindle.HUMAN)
        np.testing.assert_allclose(trace.ia_pps[:, k], ref.ia, rtol=0, atol=1e-9)
        np.testing.assert_allclose(trace.ii_pps[:, k], ref.ii, rtol=0, atol=1e-9)


def test_encoder_chain_stays_close_to_the_clean_chain():
    t, angle, t_s, counts = motion(3.0, seed=2)
    noisy = run_chain(t_s, counts=counts)
    clean = run_chain(t_s, angle_deg=np.interp(t_s, t, angle))
    # what the encoder's quantisation, noise and glitches cost (measured ~1.5 pps; Ia spans
    # ~45 pps)
    assert np.sqrt(np.mean((noisy.ia_pps - clean.ia_pps) ** 2, axis=0)).max() < 2.5
    assert np.sqrt(np.mean((noisy.ii_pps - clean.ii_pps) ** 2, axis=0)).max() < 0.8


def test_the_low_pass_makes_noisy_lengths_usable():
    rng = np.random.default_rng(4)
    t = np.arange(0, 2.0, 2e-3)
    angle = 20 + 90 * (1 - np.abs(2 * ((t % (180 / 130)) / (180 / 130)) - 1))
    clean_L = spindle.load_length_fits().length_L0(np.radians(angle))
    noisy_L = clean_L + 0.005 * rng.normal(size=clean_L.shape)
    raw_cfg = ChainConfig(lowpass_hz=None, max_speed_L0_s=MAX_SLEW_LIMIT_L0_S, backend="numpy")
    reference = run_chain(t, length_L0=clean_L, config=raw_cfg)
    raw = run_chain(t, length_L0=noisy_L, config=raw_cfg)
    filtered = run_chain(t, length_L0=noisy_L, config=ChainConfig(backend="numpy"))

    def err(trace):
        return np.sqrt(np.mean((trace.ia_pps - reference.ia_pps) ** 2))

    # measured: ~26 pps unfiltered, ~5 pps filtered (most of it the filter's 16 ms lag)
    assert err(raw) > 3 * err(filtered)


# -- bad input -------------------------------------------------------------------------------
def chain_at_rest():
    chain = ArmChain()
    chain.reset(60.0, 0.0)
    for k in range(1, 20):
        chain.push_counts(k * 2e-3, 495)
    return chain


@pytest.mark.parametrize(
    ("t_s", "counts", "counter"),
    [
        (0.05, -1, "invalid_reading"),
        (0.05, 1024, "invalid_reading"),
        (0.05, 40000, "invalid_reading"),
        (0.05, float("nan"), "invalid_reading"),
        (0.05, 500.5, "invalid_reading"),
        (0.05, None, "invalid_reading"),
        (0.038, 500, "repeated_time"),
        (0.01, 500, "time_backwards"),
        (float("nan"), 500, "bad_time"),
        (float("inf"), 500, "bad_time"),
    ],
)
def test_bad_samples_are_rejected_counted_and_change_nothing(t_s, counts, counter):
    chain = chain_at_rest()
    before = chain.spindle_state
    last = chain.last
    out = chain.push_counts(t_s, counts)
    assert not out.accepted and chain.counters[counter] == 1
    np.testing.assert_array_equal(out.ia_pps, last.ia_pps)
    after = chain.spindle_state
    np.testing.assert_array_equal(after.tension_FU, before.tension_FU)
    # and the chain then goes on exactly as if the bad sample had never come
    reference = chain_at_rest()
    for k in range(21, 40):
        a = chain.push_counts(k * 2e-3, 500)
        b = reference.push_counts(k * 2e-3, 500)
        np.testing.assert_array_equal(a.ia_pps, b.ia_pps)


def test_bad_angles_and_lengths_are_rejected():
    chain = chain_at_rest()
    assert not chain.push_angle(0.05, float("nan")).accepted
    assert not chain.push_lengths(0.05, [0.2, 1.0]).accepted
    assert not chain.push_lengths(0.05, [np.inf, 1.0]).accepted
    assert not chain.push_lengths(0.05, [1.0, 1.0, 1.0]).accepted
    assert chain.counters["invalid_angle"] == 1 and chain.counters["invalid_length"] == 3


def test_gaps_jumps_and_out_of_range_angles_follow_their_rules():
    chain = chain_at_rest()
    # a 0.2 s dropout, then the arm is found 30 deg further: longer than max_bridge_s, so
    # the chain restarts at rest there (counted, no slew limit)
    reading = 495 + round(30 / AX12.deg_per_count)
    out = chain.push_counts(0.238, reading)
    assert out.accepted and chain.counters["gaps"] == 1 and chain.counters["restarts"] == 1
    assert chain.counters["slew_limited"] == 0
    assert out.counts_filtered == reading
    assert out.angle_deg == pytest.approx(float(Calibration().angle_deg(reading)))
    # a single jump of 100 deg in 2 ms is not a motion: the median holds the first spike
    # back, and repeated jumps are slew-limited to 1000 deg/s
    t = 0.238
    angles = []
    for _ in range(10):
        t += 2e-3
        angles.append(chain.push_counts(t, 1020).angle_deg)
    assert np.abs(np.diff(angles)).max() <= 1000 * 2e-3 + 1e-9
    assert chain.counters["slew_limited"] > 0
    assert chain.counters["angle_clamped"] == 0
    for _ in range(200):
        t += 2e-3
        out = chain.push_counts(t, 1020)  # 214 deg: beyond the elbow's 130 deg
    assert out.angle_deg == pytest.approx(130.0) and chain.counters["angle_clamped"] > 0
    assert np.all(np.isfinite(out.ia_pps)) and np.all(np.isfinite(out.ii_pps))


def test_random_garbage_never_produces_nan():
    rng = np.random.default_rng(11)
    n = 3000
    t = np.cumsum(rng.choice([2e-3, 0.0, -1e-3, 0.05, np.nan], size=n, p=[.9, .03, .03, .02, .02]))
    counts = rng.choice([rng.integers(0, 1024), -1, 5000, np.nan], size=n)
    counts = np.where(rng.random(n) < 0.8, rng.integers(280, 740, size=n), counts)
    trace = run_chain(np.nan_to_num(t, nan=1.0), counts=counts.astype(float))
    for name in ("ia_pps", "ii_pps", "gamma_static_pps", "gamma_dynamic_pps", "length_L0"):
        assert np.all(np.isfinite(getattr(trace, name))), name
    assert sum(trace.counters[k] for k in COUNTERS if k != "accepted") > 0
    assert (trace.ia_pps >= 0).all()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"median_window": 6}, "median_window=6"),
        ({"lowpass_hz": 0.0}, "lowpass_hz=0.0"),
        ({"method": "rk4"}, "method='rk4'"),
        ({"step_s": 0.5}, "step=0.5"),
        ({"max_speed_L0_s": 20.0}, "max_speed_L0_s=20.0"),
        ({"backend": "fortran"}, "backend='fortran'"),
        ({"max_gap_s": -1.0}, "max_gap_s=-1.0"),
    ],
)
def test_unusable_configurations_raise_clear_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ChainConfig(**kwargs)


def test_pushing_before_reset_and_bad_batches_raise():
    with pytest.raises(RuntimeError, match="reset"):
        ArmChain().push_counts(0.0, 500)
    with pytest.raises(ValueError, match="exactly one"):
        run_chain(np.arange(3.0), counts=np.zeros(3), angle_deg=np.zeros(3))
    with pytest.raises(ValueError, match="no valid sample"):
        run_chain(np.arange(3.0), counts=np.full(3, -1))


def test_make_chain_picks_the_backend_and_the_numpy_chain_refuses_the_c_one():
    default = make_chain()  # "auto": C where the library loads here
    assert default.backend == resolve_backend("auto") == default.config.backend
    assert type(make_chain(ChainConfig(backend="numpy"))) is ArmChain
    with pytest.raises(ValueError, match=r"backend='c'.*make_chain"):
        ArmChain(ChainConfig(backend="c"))


def test_run_trace_of_the_numpy_chain_equals_single_pushes():
    _, _, t, counts = motion(0.2)
    one, whole = ArmChain(), ArmChain()
    angle0 = float(one.config.calibration.angle_deg(counts[0]))
    one.reset(angle0, t[0])
    whole.reset(angle0, t[0])
    samples = [one.push_counts(ti, ci) for ti, ci in zip(t[1:], counts[1:], strict=True)]
    stacked = whole.run_trace("push_counts", t[1:], counts[1:])
    for name, column in stacked.items():
        np.testing.assert_array_equal(column, [getattr(s, name) for s in samples])
    assert one.counters == whole.counters
    empty = whole.run_trace("push_lengths", t[:0], np.zeros((0, 2)))
    assert empty["ia_pps"].shape == (0, 2) and empty["t_s"].shape == (0,)


def test_block_pushes_equal_single_pushes():
    rng = np.random.default_rng(7)
    t = 0.002 * np.arange(1, 60)
    counts = np.round(500 + 40 * np.sin(8 * t) + rng.normal(0, 0.6, t.size))
    counts[[5, 17]] = [-1, 2000]
    one, block = ArmChain(), ArmChain()
    for chain in (one, block):
        chain.reset(angle_deg=float(Calibration().angle_deg(counts[0])), t_s=0.0)
    for ti, ci in zip(t, counts, strict=True):
        last = one.push_counts(ti, ci)
    got = block.push_counts_block(t, counts)
    assert one.counters == block.counters and one.counters["invalid_reading"] == 2
    np.testing.assert_array_equal(got.ia_pps, last.ia_pps)
    with pytest.raises(ValueError, match="expected"):
        block.push_lengths_block(t, np.ones((t.size, 3)))


def test_reset_with_exact_lengths_at_an_extreme_angle_keeps_outputs_finite():
    chain = ArmChain()
    chain.reset(angle_deg=1e308, t_s=0.0, length_L0=np.array([1.0, 1.0]))
    s = chain.push_counts(0.002, 500)
    assert np.isfinite(s.counts_filtered) and 0 <= s.counts_filtered <= AX12.max_count
    assert np.isfinite(s.angle_deg)
    assert np.isfinite(s.ia_pps).all() and np.isfinite(s.ii_pps).all()


def test_the_slew_limit_keeps_a_rounding_margin_below_the_spindles_speed_limit():
    """At exactly 10 L0/s (the spindle's limit) the C chain refused sub-steps that rounded a
    hair above it (PS_ERR_SPEED) where numpy took them; the limit is now refused, and at the
    largest accepted one the unfiltered noisy lengths that reach it run on both backends,
    equal."""
    with pytest.raises(ValueError, match=r"max_speed_L0_s=10\.0 must lie in"):
        ChainConfig(max_speed_L0_s=10.0)
    rng = np.random.default_rng(4)
    t = np.arange(0, 1.0, 2e-3)
    angle = 20 + 90 * (1 - np.abs(2 * ((t % (180 / 130)) / (180 / 130)) - 1))
    noisy_L = spindle.load_length_fits().length_L0(np.radians(angle)) + 0.005 * rng.normal(
        size=(t.size, 2))
    traces = {b: run_chain(t, length_L0=noisy_L, config=ChainConfig(
        lowpass_hz=None, max_speed_L0_s=MAX_SLEW_LIMIT_L0_S, backend=b)) for b in ("numpy", "c")}
    assert traces["c"].counters["slew_limited"] > 0  # the limit is reached
    assert traces["c"].counters == traces["numpy"].counters
    # measured 1.0e-12 pps apart (the backends' usual agreement)
    np.testing.assert_allclose(traces["c"].ia_pps, traces["numpy"].ia_pps, atol=1e-9)
