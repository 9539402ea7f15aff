"""The stimulator stage in numpy (spindle.stimulation): limits, charge balance, counts
against the rate's integral, the stochastic intervals' law, the refusal of unsafe
configurations, the handling rules, events on disk.

References: the integral of a piecewise-constant rate (a closed form); SplitMix64 written
here on Python ints; math.log; scipy.stats' gamma distribution (KS); the Shannon criterion
computed here from its definition.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from spindle.stimulation import (
    AFFERENTS,
    ELBOW_ALL,
    ELBOW_SPINDLES,
    MODES,
    Channel,
    ChannelMap,
    EncoderParams,
    StimConfig,
    StimulatorLimits,
    afferent_rates,
    charges_pC,
    generator,
    load_csv,
    load_npz,
    make_stimulator,
    save_csv,
    save_npz,
)

MASK = (1 << 64) - 1


def splitmix64_mix(x: int) -> int:
    """SplitMix64's output function (Steele et al. 2014) on Python ints."""
    z = (x + 0x9E3779B97F4A7C15) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    return z ^ (z >> 31)


def test_generator_is_splitmix64_and_its_log_is_libm_to_an_ulp():
    # SplitMix64 from state 0: its published first output
    first = int(generator.mix(np.array([0], np.uint64))[0])
    assert first == 0xE220A8397B1DCDAF == splitmix64_mix(0)
    rng = np.random.default_rng(1)
    seeds = rng.integers(0, 2**63, 50, dtype=np.uint64)
    for seed in seeds[:5]:
        ch, idx = 3, np.arange(200, dtype=np.uint64)
        want = [splitmix64_mix(splitmix64_mix(splitmix64_mix(int(seed)) ^ ch) ^ int(i))
                for i in idx]
        assert generator.draw_bits(int(seed), ch, idx).tolist() == want
    u = generator.uniform(7, np.arange(4)[:, None], np.arange(50_000))
    assert 0 < u.min() and u.max() < 1
    ref = np.array([math.log(x) for x in u.ravel()])
    # measured: 3.7e-16 relative at most
    assert np.max(np.abs(generator.log_unit(u).ravel() - ref) / np.abs(ref)) < 1e-15


def piecewise_integral(rates: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Cumulative integral at the sample boundaries (T+1, channels)."""
    return np.vstack([np.zeros(rates.shape[1]), np.cumsum(rates * dt[:, None], axis=0)])


def channels_strategy(n: int) -> st.SearchStrategy:
    def channel(k: int) -> st.SearchStrategy:
        return st.builds(
            lambda thr, span, phase, gap: Channel("M", AFFERENTS[k % 3] if n <= 3 else "ia",
                                                  thr, thr + span, phase, gap, 1e-3),
            st.integers(1, 100), st.integers(0, 100), st.integers(20, 400), st.integers(0, 200))
    if n > 3:  # distinct muscles when more channels than afferent kinds
        return st.tuples(*[channel(k).map(
            lambda c, k=k: Channel(f"M{k}", c.afferent, c.threshold_uA, c.max_uA,
                                   c.phase_us, c.gap_us, c.area_cm2)) for k in range(n)]
        ).map(ChannelMap)
    return st.tuples(*[channel(k) for k in range(n)]).map(ChannelMap)


@st.composite
def scenario(draw, mode: str | None = None):
    n = draw(st.integers(1, 5))
    channels = draw(channels_strategy(n))
    longest_us = max(c.duration_us for c in channels.channels)
    max_rate = draw(st.floats(20.0, min(1000.0, 0.45e6 / longest_us)))
    total = draw(st.one_of(st.none(), st.floats(10.0, 3000.0)))
    limits = StimulatorLimits(max_rate_pps=max_rate, max_total_rate_pps=total)
    mode = mode or draw(st.sampled_from(sorted(MODES)))
    dead = draw(st.floats(longest_us * 1e-6, 0.9 / max_rate))
    params = EncoderParams(mode=mode, carrier_pps=min(100.0, max_rate), dead_time_s=dead,
                           gamma_shape=draw(st.integers(1, 4)),
                           seed=draw(st.integers(0, 2**64 - 1)))
    T = draw(st.integers(1, 60))
    dt = np.array(draw(st.lists(st.floats(1e-4, 0.02), min_size=T, max_size=T)))
    rates = np.array(draw(st.lists(st.lists(st.floats(-50.0, 2.0 * max_rate), min_size=n,
                                            max_size=n), min_size=T, max_size=T)))
    return StimConfig(channels, limits, params), rates, dt


def assert_within_limits(config: StimConfig, events: np.ndarray) -> None:
    chans, lim = config.channels.channels, config.limits
    t = events["time_s"]
    assert np.all(np.diff(t) >= 0)  # time order
    cath, anod = charges_pC(events)
    assert np.array_equal(cath, anod)  # charge balance, exact integers
    for k, c in enumerate(chans):
        mine = events[events["channel"] == k]
        assert np.all((mine["amplitude_uA"] >= c.threshold_uA) & (mine["amplitude_uA"] <= c.max_uA))
        assert np.all(mine["cathodic_us"] == c.phase_us) and np.all(mine["gap_us"] == c.gap_us)
        gaps = np.diff(mine["time_s"])
        assert np.all(gaps >= (c.duration_us + lim.min_interval_us) * 1e-6 * (1 - 1e-12))
        if not MODES[config.params.mode].stochastic:  # the pulse rate never exceeds the max
            assert np.all(gaps >= (1.0 / lim.max_rate_pps) * (1 - 1e-9))
        assert np.all(mine["amplitude_uA"].astype(np.int64) * c.phase_us
                      <= lim.max_charge_nC * 1e3)
    if lim.max_total_rate_pps is not None:
        assert np.all(np.diff(t) >= (1.0 / lim.max_total_rate_pps) * (1 - 1e-12))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenario())
def test_no_limit_is_ever_violated_and_every_pulse_is_balanced(case):
    config, rates, dt = case
    stim = make_stimulator(config, backend="numpy")
    events = stim.run(rates, dt)
    assert_within_limits(config, events)
    assert stim.counters["pulses"] == events.size
    assert events["time_s"].min(initial=0.0) >= 0.0 and events["time_s"].max(initial=0) < dt.sum()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scenario(mode="frequency"), st.data())
def test_deterministic_counts_are_the_integral_within_one_pulse(case, data):
    config, rates, dt = case
    config = StimConfig(config.channels, StimulatorLimits(config.limits.max_rate_pps),
                        config.params)  # no total-rate limit: nothing is dropped
    events = make_stimulator(config, backend="numpy").run(rates, dt)
    requested = np.clip(rates, 0.0, config.limits.max_rate_pps)
    integral = piecewise_integral(requested, dt)
    edges = np.concatenate([[0.0], np.cumsum(dt)])
    a = data.draw(st.integers(0, len(dt)))
    b = data.draw(st.integers(a, len(dt)))
    for k in range(config.n_channels):
        t = events["time_s"][events["channel"] == k]
        count = np.sum((t >= edges[a]) & (t < edges[b]))
        assert abs(count - (integral[b, k] - integral[a, k])) <= 1.0 + 1e-9
        # from the start: the count is the integral's floor (a pulse per whole crossing)
        assert np.sum(t < edges[b]) in (math.floor(integral[b, k] + 1e-9),
                                        math.floor(integral[b, k] - 1e-9))


def test_bad_rates_follow_the_counted_rules_and_never_burst():
    config = StimConfig(params=EncoderParams(mode="biomimetic"))
    stim = make_stimulator(config, backend="numpy")
    rates = np.full((50, 4), 40.0)
    rates[10] = [np.nan, np.inf, -np.inf, 1e300]
    rates[11] = [-5.0, 40.0, 40.0, 40.0]
    events = stim.run(rates, 0.002)
    c = stim.channel_counters
    assert stim.counters["rate_nonfinite"] == 3 and stim.counters["rate_negative"] == 1
    assert stim.counters["rate_clipped"] == 1
    assert c[0, 1] == 1 and c[1, 1] == 1 and c[2, 1] == 1 and c[3, 3] == 1 and c[0, 2] == 1
    t = events["time_s"]
    for k in range(3):  # stopped for the bad interval: no pulse in it
        assert not np.any((events["channel"] == k) & (t >= 0.020) & (t < 0.022))
    huge = t[(events["channel"] == 3) & (t >= 0.020) & (t < 0.022)]
    assert huge.size <= 300 * 0.002 + 1  # clipped to max_rate_pps: at most one pulse
    assert_within_limits(config, events)


def test_stochastic_intervals_follow_the_gamma_law_with_dead_time():
    """Constant rate r: intervals are dead + gamma(k, 1/(k r')), r' = r / (1 - r dead).

    KS at a fixed seed, alpha = 1e-3 (the false-alarm rate if the law holds); the same test
    rejects the law without the dead time, so it has the power to see a wrong one."""
    stats = pytest.importorskip("scipy.stats")
    r, dead = 80.0, 2e-3
    for k, seed in ((1, 11), (3, 12)):
        config = StimConfig(ChannelMap((Channel("BRA", "ia"),)),
                            params=EncoderParams(mode="stochastic", gamma_shape=k,
                                                 dead_time_s=dead, seed=seed))
        stim = make_stimulator(config, backend="numpy")
        events = stim.run(np.full((1500, 1), r), 0.02)  # 30 s
        isi = np.diff(events["time_s"])
        rp = r / (1 - r * dead)
        assert stats.kstest(isi, stats.gamma(k, loc=dead, scale=1 / (k * rp)).cdf).pvalue > 1e-3
        assert stats.kstest(isi, stats.gamma(k, scale=1 / (k * r)).cdf).pvalue < 1e-6
        # mean rate: 2400 pulses expected; sd sqrt(N) for Poisson, less for k > 1
        assert abs(events.size - r * 30.0) < 4 * math.sqrt(r * 30.0)
        assert isi.min() >= dead


def test_amplitude_coding_is_the_linear_map_from_threshold_to_maximum():
    channel = Channel("BRA", "ia", threshold_uA=20, max_uA=120)
    config = StimConfig(ChannelMap((channel,)),
                        params=EncoderParams(mode="amplitude", full_scale_pps=100.0,
                                             carrier_pps=50.0))
    for rate in (1.0, 33.3, 75.0, 100.0, 250.0):
        stim = make_stimulator(config, backend="numpy")
        events = stim.run(np.full((500, 1), rate), 0.002)
        want = math.floor(20 + 100 * min(rate / 100.0, 1.0) + 0.5)
        assert set(events["amplitude_uA"].tolist()) == {want}
        # 50 pps for 1 s: crossings at k / 50 s; the 50th, at t = 1 s, sits on the end of
        # the last interval, where rounding of the summed intervals decides
        assert events.size in (49, 50)
        assert np.max(np.abs(events["time_s"] - np.arange(1, events.size + 1) / 50)) < 1e-12
        assert stim.counters["amplitude_clipped"] == (500 if rate > 100 else 0)


def test_biomimetic_mode_maps_level_and_change():
    p = EncoderParams(mode="biomimetic", full_scale_pps=100.0, full_scale_change_pps_s=1000.0)
    config = StimConfig(ChannelMap((Channel("BRA", "ia", 30, 150),)), params=p)
    stim = make_stimulator(config, backend="numpy")
    flat = stim.run(np.full((1000, 1), 50.0), 0.002)  # 2 s at half scale, no change
    assert abs(flat.size - 300 * 0.5 * 0.5 * 2.0) <= 1  # 75 pps
    assert set(flat["amplitude_uA"].tolist()) == {math.floor(30 + 120 * 0.5 + 0.5)}
    ramp = np.linspace(0.0, 50.0, 100)[:, None]  # 505 pps/s for 0.1 s: d = 0.505
    events = make_stimulator(config, backend="numpy").run(ramp, 0.001)
    assert events.size > 3
    i = np.floor(events["time_s"] / 1e-3 + 1e-9).astype(int)  # the sample each pulse is in
    d = np.where(i > 0, 50.0 / 99 / 1e-3 / 1000.0, 0.0)
    want = np.floor(30 + 120 * np.minimum(ramp[i, 0] / 100.0 + 0.5 * d, 1.0) + 0.5)
    assert np.array_equal(events["amplitude_uA"], want)


def test_streaming_equals_batch():
    config = StimConfig(ELBOW_ALL, params=EncoderParams(mode="stochastic", seed=5))
    rng = np.random.default_rng(3)
    rates = rng.uniform(0, 150, (300, 6))
    dt = rng.uniform(1e-3, 3e-3, 300)
    batch = make_stimulator(config, backend="numpy").run(rates, dt)
    stim = make_stimulator(config, backend="numpy")
    streamed = np.concatenate([stim.step(rates[i], dt[i]) for i in range(300)])
    assert np.array_equal(batch, streamed)


def test_unsafe_or_impossible_configurations_are_refused_naming_value_and_limit():
    area = 2e-5  # cm²
    q_uC = 150 * 200 * 1e-6
    k = math.log10(q_uC) + math.log10(q_uC / area)  # 1.35: safe at k_max 1.85
    StimConfig(ChannelMap((Channel("BRA", "ia", 30, 150, 200, 50, area),)))
    with pytest.raises(ValueError, match=rf"Shannon k = {k:.3f}, above the limit shannon_k=1"):
        StimConfig(ChannelMap((Channel("BRA", "ia", 30, 150, 200, 50, area),)),
                   StimulatorLimits(shannon_k=1.0))
    with pytest.raises(ValueError, match=r"30 nC per phase exceeds the limit max_charge_nC=20"):
        StimConfig(ChannelMap((Channel("BRA", "ia", 30, 150, 200, 50, 1e-2),)),
                   StimulatorLimits(max_charge_nC=20.0))
    with pytest.raises(ValueError, match=r"takes 4500 µs .* longer than the 1/max_rate_pps"):
        StimConfig(ChannelMap((Channel("BRA", "ia", 30, 150, 2000, 500, 1.0),)),
                   StimulatorLimits(max_rate_pps=300.0, max_charge_nC=1e3))
    with pytest.raises(ValueError, match=r"dead_time_s=0\.0001 is shorter"):
        StimConfig(params=EncoderParams(mode="stochastic", dead_time_s=1e-4))
    with pytest.raises(ValueError, match=r"max_rate_pps \* dead_time_s = 1\.5 must be < 1"):
        StimConfig(params=EncoderParams(mode="stochastic", dead_time_s=5e-3))
    with pytest.raises(ValueError, match="carrier_pps=400 exceeds max_rate_pps=300"):
        StimConfig(params=EncoderParams(mode="amplitude", carrier_pps=400.0))
    with pytest.raises(ValueError, match="threshold_uA=200 exceeds max_uA=150"):
        Channel("BRA", "ia", 200, 150)
    with pytest.raises(TypeError, match=r"phase_us=100\.5 must be an int"):
        Channel("BRA", "ia", phase_us=100.5)
    with pytest.raises(ValueError, match="afferent='ic' is not one of"):
        Channel("BRA", "ic")
    with pytest.raises(ValueError, match=r"\('BRA', 'ia'\) drives more than one channel"):
        ChannelMap((Channel("BRA", "ia"), Channel("BRA", "ia")))
    with pytest.raises(ValueError, match="mode='fm' is not one of"):
        EncoderParams(mode="fm")


def test_a_refused_call_leaves_the_state_as_it_was():
    stim = make_stimulator(StimConfig(params=EncoderParams(mode="stochastic")), "numpy")
    stim.run(np.full((20, 4), 60.0), 0.002)
    before = stim.state.copy()
    for rates, dt in (([1.0, 2.0], 0.002), ([1.0] * 4, 0.0), ([1.0] * 4, np.nan),
                      ([1.0] * 4, 2.0), ([1j] * 4, 0.002)):
        with pytest.raises(ValueError):
            stim.step(rates, dt)
    with pytest.raises(ValueError, match=r"dt_s\[3\]=-1.0"):
        stim.run(np.ones((5, 4)), [0.002, 0.002, 0.002, -1.0, 0.002])
    for name, value in vars(before).items():
        assert np.array_equal(getattr(stim.state, name), value, equal_nan=True), name


def test_channel_map_takes_ib_and_gathers_rates_by_pair():
    assert ELBOW_ALL.index("TRImed", "ib") == 5
    ia, ii, ib = (np.arange(6.0).reshape(3, 2) + s for s in (0, 10, 20))
    rates = ELBOW_ALL.gather(afferent_rates(("BRA", "TRImed"), ia=ia, ii=ii, ib=ib))
    assert rates.shape == (3, 6)
    assert np.array_equal(rates[:, 2], ib[:, 0]) and np.array_equal(rates[:, 3], ia[:, 1])
    with pytest.raises(KeyError, match=r"BRA ib"):
        ELBOW_ALL.gather(afferent_rates(("BRA", "TRImed"), ia=ia, ii=ii))
    assert ELBOW_SPINDLES.gather(afferent_rates(("BRA", "TRImed"), ia=ia[0], ii=ii[0],
                                                ib=ib[0])).shape == (4,)


def test_events_round_trip_through_csv_and_npz(tmp_path):
    config = StimConfig(params=EncoderParams(mode="biomimetic"))
    rng = np.random.default_rng(0)
    events = make_stimulator(config, "numpy").run(rng.uniform(0, 200, (400, 4)), 0.002)
    assert events.size > 100
    save_npz(tmp_path / "e.npz", events, config.channels.labels)
    got, labels = load_npz(tmp_path / "e.npz")
    assert np.array_equal(got, events) and labels == config.channels.labels
    save_csv(tmp_path / "e.csv", events, config.channels.labels)
    back = load_csv(tmp_path / "e.csv")
    assert np.max(np.abs(back["time_s"] - events["time_s"])) <= 5e-10
    for name in ("channel", "amplitude_uA", "cathodic_us", "gap_us", "anodic_us"):
        assert np.array_equal(back[name], events[name])
    assert (tmp_path / "e.csv").read_text().splitlines()[0].endswith(",label")


def test_plot_raster_draws_a_row_per_channel_with_its_rate():
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(200) * 0.002
    rates = np.stack([np.full(200, 50.0), np.linspace(0, 150, 200)], axis=1)
    config = StimConfig(ChannelMap((Channel("BRA", "ia", 30, 150), Channel("BRA", "ii", 30, 150))),
                        params=EncoderParams(mode="amplitude", full_scale_pps=150.0))
    events = make_stimulator(config, "numpy").run(rates, 0.002)
    fig, ax = plt.subplots()
    from spindle.stimulation import plot_raster

    plot_raster(ax, events, config.channels.labels, t, rates)
    ticks = ax.collections
    assert len(ticks) == 2 and len(ax.lines) == 2
    assert [s.get_text() for s in ax.get_yticklabels()] == ["BRA ii", "BRA ia"]
    # channel 0 (top row, y from 1): one tick per pulse; heights grow with amplitude
    segs = ticks[0].get_segments()
    assert len(segs) == np.sum(events["channel"] == 0)
    heights = [s[1, 1] - s[0, 1] for s in ticks[1].get_segments()]
    assert heights[-1] > heights[0]
    plt.close(fig)


@pytest.mark.slow
def test_the_stimulation_experiment_writes_its_figure_and_events(tmp_path):
    pytest.importorskip("matplotlib")
    from proprio_env.experiments import stimulation

    numbers = stimulation.run(tmp_path, duration_s=2.0)
    for mode in MODES:
        events, labels = load_npz(tmp_path / f"stimulation_{mode}.npz")
        assert labels == ELBOW_SPINDLES.labels
        assert np.array_equal(load_csv(tmp_path / f"stimulation_{mode}.csv")["channel"],
                              events["channel"])
    assert (tmp_path / "stimulation.png").stat().st_size > 10_000
    for label, integral in numbers.integral.items():  # frequency coding: the integral's floor
        assert abs(numbers.pulses["frequency"][label] - integral) <= 1.0
