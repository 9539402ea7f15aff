"""The C stimulator (stimulation.c) against the numpy encoder, and its fixed-point form
against the double one.

numpy and C run the same operations in the same order, so the double form's events are
compared for equality (bit for bit, stochastic trains included: the counter-based generator
and its log are written alike); the fixed-point form (Q16 rates, whole µs, an integer log) is
compared with the double form at the same quantised rates: the same pulses per channel,
times within the microsecond tick it rounds up to (deterministic modes) or the few µs its
dead time's restart on a whole µs gives (stochastic; measured below), amplitudes within
1 µA off the sample boundaries. The demo motion is the demo's (servo, encoder, chain).
"""

from __future__ import annotations

import ctypes
import math
import re
import subprocess

import numpy as np
import pytest
from c_layout import c_layout
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sanitized_build import SANITIZER_REPORT
from sanitized_build import build as sanitized

from spindle.native import abi, build
from spindle.native import stimulation as cstim
from spindle.stimulation import (
    COUNTERS,
    MAX_CHANNELS,
    MODES,
    PULSE_DTYPE,
    Channel,
    ChannelMap,
    EncoderParams,
    StimConfig,
    StimulatorLimits,
    generator,
    intervals_from_times,
    make_stimulator,
)

try:
    build.find_compiler()
except build.CBackendError as exc:  # pragma: no cover - depends on the machine
    pytest.skip(str(exc), allow_module_level=True)

Status = abi.Status


@pytest.fixture(scope="module")
def demo() -> tuple[np.ndarray, np.ndarray]:
    from proprio_env.experiments.stimulation import demo_rates

    return demo_rates(1.5, seed=0)


def configs() -> list[StimConfig]:
    out = [StimConfig(params=EncoderParams(mode=m, seed=9)) for m in MODES]
    out += [StimConfig(limits=StimulatorLimits(max_total_rate_pps=40.0),
                       params=EncoderParams(mode=m, seed=9)) for m in MODES]
    return out


def test_header_constants_status_and_layouts(tmp_path):
    header = abi.header_constants()
    assert {s.name: s.value for s in abi.Status} == abi.header_status_codes()
    assert header["PS_STIM_MAX_CHANNELS"] == MAX_CHANNELS
    assert header["PS_STIM_COUNTERS"] == len(COUNTERS)
    for name, mode in MODES.items():
        assert header[f"PS_STIM_MODE_{name.upper()}"] == mode.code
    for k, name in enumerate(COUNTERS):
        assert header[f"PS_STIM_COUNT_{name.upper()}"] == k
    text = build.HEADER.read_text()  # an LL literal, which header_constants does not read
    assert f"#define PS_STIM_FX_PULSE {cstim.FX_PULSE}LL" in text
    assert header["PS_STIM_FX_RATE_ONE"] == cstim.FX_RATE_ONE
    structs = [("ps_stim_config", cstim.PsStimConfig, f) for f in ("channel", "max_rate_pps",
                                                                     "seed")]
    structs += [("ps_stim_state", cstim.PsStimState, f) for f in ("draws", "counts", "ready")]
    structs += [("ps_pulse", cstim.PsPulse, "anodic_us"),
                ("ps_stim_channel", cstim.PsStimChannel, "area_cm2"),
                ("ps_stim_fx_config", cstim.PsStimFxConfig, "seed"),
                ("ps_stim_fx_state", cstim.PsStimFxState, "counts"),
                ("ps_stim_fx_state", cstim.PsStimFxState, "ready"),
                ("ps_pulse_fx", cstim.PsPulseFx, "anodic_us")]
    got = [(ctypes.sizeof(py), getattr(py, f).offset) for _, py, f in structs]
    assert got == c_layout([(c, f) for c, _, f in structs], tmp_path)
    assert PULSE_DTYPE.itemsize == ctypes.sizeof(cstim.PsPulse)
    assert cstim.PULSE_FX_DTYPE.itemsize == ctypes.sizeof(cstim.PsPulseFx)


def test_generator_bits_and_draws_are_identical():
    lib = cstim.library()
    rng = np.random.default_rng(4)
    for seed in [0, 2**64 - 1, *rng.integers(0, 2**63, 2).tolist()]:
        idx = np.arange(200, dtype=np.uint64)
        for ch in (0, 5, 15):
            bits = [lib.ps_stim_bits(seed, ch, int(i)) for i in idx]
            assert generator.draw_bits(seed, ch, idx).tolist() == bits
            u = generator.uniform(seed, ch, idx)
            assert u.tolist() == [lib.ps_stim_uniform(seed, ch, int(i)) for i in idx]
            assert generator.log_unit(u).tolist() == [lib.ps_stim_log_unit(x) for x in u]
            for shape in (1, 3, 16):
                got = [lib.ps_stim_gamma_threshold(seed, ch, int(i), shape) for i in idx[:50]]
                assert generator.gamma_threshold(seed, ch, idx[:50], shape).tolist() == got


def config_id(c: StimConfig) -> str:
    return f"{c.params.mode}-{'total' if c.limits.max_total_rate_pps else 'free'}"


@pytest.mark.parametrize("config", configs(), ids=[config_id(c) for c in configs()])
def test_numpy_equals_c_on_the_demo_motion(demo, config):
    t_s, rates = demo
    dt = intervals_from_times(t_s)
    ref = make_stimulator(config, "numpy", t0_s=float(t_s[0]))
    got = make_stimulator(config, "c", t0_s=float(t_s[0]))
    assert got.backend == "c"
    a, b = ref.run(rates, dt), got.run(rates, dt)
    assert a.size > 20
    assert np.array_equal(a, b)  # bit for bit: times, channels, amplitudes
    assert np.array_equal(ref.channel_counters, got.channel_counters)
    assert ref.t_s == got.t_s


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mode=st.sampled_from(sorted(MODES)), seed=st.integers(0, 2**64 - 1),
       total=st.one_of(st.none(), st.floats(20.0, 2000.0)), n=st.integers(1, 6),
       data=st.data())
def test_numpy_equals_c_on_random_rates_and_bad_samples(mode, seed, total, n, data):
    channels = ChannelMap(tuple(Channel(f"M{k}", "ia", 10 + k, 100 + 5 * k, 50 + 10 * k, 20 * k)
                                for k in range(n)))
    config = StimConfig(channels, StimulatorLimits(max_rate_pps=400.0, max_total_rate_pps=total),
                        EncoderParams(mode=mode, seed=seed, gamma_shape=1 + seed % 3))
    T = data.draw(st.integers(1, 80))
    values = st.one_of(st.floats(-20.0, 600.0), st.sampled_from([np.nan, np.inf, -np.inf,
                                                                  1e308]))
    rates = np.array(data.draw(st.lists(st.lists(values, min_size=n, max_size=n),
                                        min_size=T, max_size=T)))
    dt = np.array(data.draw(st.lists(st.floats(1e-4, 0.05), min_size=T, max_size=T)))
    a = make_stimulator(config, "numpy")
    b = make_stimulator(config, "c")
    assert np.array_equal(a.run(rates, dt), b.run(rates, dt))
    assert np.array_equal(a.channel_counters, b.channel_counters)


def test_a_full_buffer_is_an_error_and_changes_nothing():
    lib = cstim.library()
    config = StimConfig(params=EncoderParams(mode="stochastic"))
    c = cstim.config_struct(config)
    s = cstim.PsStimState()
    assert lib.ps_stim_init(ctypes.byref(s), ctypes.byref(c), 0.0) == Status.PS_OK
    rates = np.full(4, 250.0)
    ev = (cstim.PsPulse * 64)()
    n = ctypes.c_long()
    dbl = ctypes.POINTER(ctypes.c_double)
    before = bytes(s)
    # the exact count of this step (a bound-sized buffer cannot fill)
    bound = lib.ps_stim_max_events(ctypes.byref(c), 0.05)
    assert bound == 4 * (int(0.05 / 2e-3) + 2)
    probe = cstim.PsStimState.from_buffer_copy(before)
    assert lib.ps_stim_step(ctypes.byref(probe), ctypes.byref(c), rates.ctypes.data_as(dbl),
                            0.05, ev, 64, ctypes.byref(n)) == Status.PS_OK
    need = n.value
    assert 10 < need < bound
    code = lib.ps_stim_step(ctypes.byref(s), ctypes.byref(c), rates.ctypes.data_as(dbl), 0.05,
                            ev, need - 1, ctypes.byref(n))
    assert code == Status.PS_ERR_BUFFER_FULL and n.value == 0 and bytes(s) == before
    assert lib.ps_stim_step(ctypes.byref(s), ctypes.byref(c), rates.ctypes.data_as(dbl), 0.05,
                            ev, need, ctypes.byref(n)) == Status.PS_OK
    assert n.value == need and bytes(s) == bytes(probe)
    assert lib.ps_stim_step(ctypes.byref(s), ctypes.byref(c), rates.ctypes.data_as(dbl), 2.0,
                            ev, 64, ctypes.byref(n)) == Status.PS_ERR_STEP
    fresh = cstim.PsStimState()
    assert lib.ps_stim_step(ctypes.byref(fresh), ctypes.byref(c), rates.ctypes.data_as(dbl),
                            0.01, ev, 64, ctypes.byref(n)) == Status.PS_ERR_NOT_RESET


def test_the_c_stimulator_refuses_what_numpy_refuses_and_keeps_its_state():
    config = StimConfig(params=EncoderParams(mode="stochastic"))
    stim = make_stimulator(config, "c")
    stim.run(np.full((20, 4), 60.0), 0.002)
    before = bytes(stim.state)
    for rates, dt, match in (([1.0, 2.0], 0.002, r"shape \(2,\), expected \(4,\)"),
                             ([1.0] * 4, 0.0, "dt_s=0.0 must be"), ([1.0] * 4, 2.0, "dt_s=2.0"),
                             ([1j] * 4, 0.002, "must be real")):
        with pytest.raises(ValueError, match=match):
            stim.step(rates, dt)
    with pytest.raises(ValueError, match=r"dt_s\[1\]=nan"):
        stim.run(np.ones((3, 4)), [0.002, np.nan, 0.002])
    assert bytes(stim.state) == before


def test_c_refuses_unsafe_configurations_by_status():
    """The checks of StimConfig, done again by the C port for C callers (raw structs)."""
    lib = cstim.library()
    good = cstim.config_struct(StimConfig())
    assert lib.ps_stim_config_check(ctypes.byref(good)) == Status.PS_OK

    def changed(**fields) -> int:
        c = cstim.PsStimConfig.from_buffer_copy(bytes(good))
        for name, value in fields.items():
            if name.startswith("ch0_"):
                setattr(c.channel[0], name[4:], value)
            else:
                setattr(c, name, value)
        return lib.ps_stim_config_check(ctypes.byref(c))

    # Shannon: 150 µA x 100 µs on 1e-6 cm² gives k = log10(0.015) + log10(0.015 / 1e-6) = 2.35
    assert math.log10(0.015) + math.log10(0.015 / 1e-6) > 1.85
    assert changed(ch0_area_cm2=1e-6) == Status.PS_ERR_CHARGE
    assert changed(max_charge_nC=10.0) == Status.PS_ERR_CHARGE
    assert changed(ch0_phase_us=2000, ch0_area_cm2=1.0, max_charge_nC=1e3) == \
        Status.PS_ERR_CONFIG  # longer than 1 / max rate
    assert changed(n_channels=17) == Status.PS_ERR_CONFIG
    assert changed(max_rate_pps=float("nan")) == Status.PS_ERR_CONFIG
    assert changed(ch0_threshold_uA=200) == Status.PS_ERR_CONFIG
    assert changed(mode=1, dead_time_s=5e-3) == Status.PS_ERR_CONFIG  # max_rate * dead >= 1
    assert changed(mode=1, dead_time_s=1e-4) == Status.PS_ERR_CONFIG  # shorter than a pulse
    assert lib.ps_stim_config_check(None) == Status.PS_ERR_NULL


def test_fixed_log_is_the_log():
    lib = cstim.fixed_library()
    bits = generator.draw_bits(3, 1, np.arange(20_000, dtype=np.uint64))
    got = np.array([lib.ps_stim_fx_neg_log(int(b)) for b in bits]) / 2**30
    u = generator.uniform(3, 1, np.arange(20_000, dtype=np.uint64))
    # measured: 4.0e-9 at most (Q30 steps, the series' and y's truncations)
    assert np.max(np.abs(got + np.log(u))) < 5e-9


def sorted_by_channel(events: np.ndarray, time_field: str) -> np.ndarray:
    return events[np.lexsort((events[time_field], events["channel"]))]


def pulse_rate_pps(mode: str, r: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """The pulse rate each mode integrates (default EncoderParams and limits), in closed
    form: the afferent rate, r / (1 - r dead), the carrier, or the biomimetic map."""
    if mode == "frequency":
        return r
    if mode == "stochastic":
        return r / (1 - r * 2e-3)
    if mode == "amplitude":
        return np.where(r > 0, 100.0, 0.0)
    change = np.abs(np.diff(r, axis=0, prepend=r[:1])) / dt[:, None]
    return 300 * np.minimum(0.5 * np.minimum(r / 100, 1) + 0.5 * np.minimum(change / 2000, 1), 1)


@pytest.mark.parametrize("mode", sorted(MODES))
def test_fixed_point_equals_double_on_the_demo_motion(demo, mode):
    """Same pulses per channel; each pulse's time within what a microsecond's tick of its
    integral allows: |dt| * pulse rate <= 1.2e-4 pulse (measured on 6 s: 4.5e-5 frequency,
    9.0e-5 stochastic, 1e-11 amplitude, 7.0e-5 biomimetic; so < 1 µs at 100 pps, more where
    the rate is near zero: 49 µs at most, stochastic, median 1.6 µs)."""
    t_s, rates = demo
    t_us = np.round((t_s - t_s[0]) * 1e6).astype(np.int64)
    dt_us = np.append(np.diff(t_us), np.diff(t_us)[-1])
    q = cstim.to_q16(rates)
    r, dt = q / 65536.0, dt_us * 1e-6
    config = StimConfig(params=EncoderParams(mode=mode, seed=9))
    double = make_stimulator(config, "c").run(r, dt)
    fixed, counts = cstim.fixed_run(config, q, dt_us)
    assert double.size > 20
    a, b = sorted_by_channel(double, "time_s"), sorted_by_channel(fixed, "time_us")
    assert np.array_equal(a["channel"], b["channel"])  # the same pulses per channel
    err_s = np.abs(a["time_s"] - b["time_us"] * 1e-6)
    edges = np.concatenate([[0.0], np.cumsum(dt)])
    sample = np.searchsorted(edges, a["time_s"], side="right") - 1
    f = pulse_rate_pps(mode, r, dt)[sample, a["channel"]]
    assert np.max(err_s * f) <= 1.2e-4
    assert np.median(err_s) <= 2e-6
    near_edge = np.min(np.abs(a["time_s"][:, None] - edges[None, :]), axis=1) < 2e-6
    da = np.abs(a["amplitude_uA"] - b["amplitude_uA"])
    assert da[~near_edge].max(initial=0) <= 1
    assert np.array_equal(counts[:, 0], np.bincount(b["channel"], minlength=4))
    assert np.all(b["cathodic_us"] == b["anodic_us"])


@pytest.mark.slow
@pytest.mark.parametrize("mode", sorted(MODES))
def test_cortex_m0plus_firmware_gives_the_host_fixed_point_events(demo, mode, tmp_path):
    """The firmware (firmware.c with FW_STIM, arm-none-eabi-gcc, emulated) on 0.5 s of the
    demo motion: the same events as the host build of the fixed form, bit for bit."""
    import shutil

    if shutil.which("arm-none-eabi-gcc") is None:
        pytest.skip("arm-none-eabi-gcc not installed (apt-get install gcc-arm-none-eabi)")
    pytest.importorskip("unicorn")
    from spindle.native.m0plus import stim

    t_s, rates = demo
    keep = t_s <= t_s[0] + 0.5
    t_us = np.round((t_s[keep] - t_s[0]) * 1e6).astype(np.int64)
    dt_us = np.append(np.diff(t_us), np.diff(t_us)[-1])
    q = cstim.to_q16(rates[keep])
    config = StimConfig(params=EncoderParams(mode=mode, seed=9))
    measured = stim.emulate_stim(config, q, dt_us, tmp_path)
    host, _ = cstim.fixed_run(config, q, dt_us)
    assert host.size > 5 and np.array_equal(measured.events, host)


def test_sanitizer_fuzz_of_the_stimulator(tmp_path):
    """fuzz/fuzz_stim.c under ASan + UBSan: random configs (some broken), rates (NaN, inf,
    huge, negative; int32 extremes), intervals and buffer sizes; the header's promises
    checked by the driver, zero sanitizer reports."""
    source = build.SOURCE_DIR / "fuzz" / "fuzz_stim.c"
    binary = sanitized(tmp_path / "fuzz_stim",
                       [build.SOURCE_DIR / "stimulation.c", source], "double")
    result = subprocess.run([str(binary), "1", "3000"], capture_output=True, text=True,
                            timeout=600)
    report = result.stdout + result.stderr
    assert result.returncode == 0 and not SANITIZER_REPORT.search(report), report[-3000:]
    counts = {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", result.stdout)}
    assert counts["iterations"] == 3000 and counts["ok"] > 3000 and counts["refused"] > 1000
