"""The C chain (spindle/native/c/chain.c, backend="c") against the numpy chain, sample by sample.

The numpy chain is the reference: it is tested against scipy references in test_chain.py.
Every ArmSample field of the double build must agree to round-off (TOL), and the
counters exactly, on realistic traces full of the bad samples each handling rule is for.
"""

import ctypes
import math
import shutil
import subprocess
from dataclasses import fields, replace

import numpy as np
import pytest

from proprio_env.body.encoder import Encoder
from spindle.chain import (
    COUNTERS,
    MUSCLES,
    ArmChain,
    ArmSample,
    ChainConfig,
    make_chain,
    run_chain,
)
from spindle.chain.length_model import load_length_fits
from spindle.chain.sensor import AX12
from spindle.native import abi, build

try:
    build.find_compiler()
except build.CBackendError:  # pragma: no cover - CI has a compiler
    pytest.skip("no C compiler: the C backend cannot be built", allow_module_level=True)

from spindle.native import chain as native_chain

TOL = 5e-12
"""Double C chain vs numpy chain, any ArmSample field. Measured (2026-12-02) at most 1.7e-12
(TRImed acceleration, L0/s^2), 1.05e-12 pps (Ia), 2.4e-13 pps (II), 6.7e-15 L0/s (velocity);
angles, lengths, templates, counts and drives bit for bit or within 1.1e-16."""
C = ChainConfig(backend="c")


def triangle(duration_s=2.0, dt=1e-3, speed_deg_s=130.0):
    t = np.arange(0.0, duration_s, dt)
    period = 2 * 90 / speed_deg_s
    return t, 20 + 90 * (1 - np.abs(2 * ((t % period) / period) - 1))


def encoder_trace(duration_s=2.0, seed=0, invalid_rate=0.01):
    t, angle = triangle(duration_s)
    enc = Encoder(replace(AX12, invalid_rate=invalid_rate), rng=seed)
    return enc.record(t, angle)


def assert_same(numpy_out: ArmSample, c_out: ArmSample, where: str, tol: float = TOL) -> None:
    assert c_out.accepted == numpy_out.accepted, where
    for f in fields(ArmSample):
        a = np.asarray(getattr(numpy_out, f.name), dtype=float)
        b = np.asarray(getattr(c_out, f.name), dtype=float)
        assert a.shape == b.shape, (where, f.name)
        err = np.max(np.abs(a - b))
        assert err <= tol, f"{where}: {f.name} numpy {a} vs C {b} (|diff| {err:.3g})"


def pair():
    return ArmChain(ChainConfig()), make_chain(C)


# -- construction and build -----------------------------------------------------------------
def test_backend_c_builds_a_c_chain_with_the_numpy_chains_ranges():
    numpy_chain, c_chain = pair()
    assert isinstance(c_chain, native_chain.CArmChain) and not isinstance(c_chain, ArmChain)
    assert (c_chain.backend, c_chain.config.backend, numpy_chain.backend) == ("c", "c", "numpy")
    assert type(numpy_chain) is ArmChain
    # the fitted range in degrees and each muscle's range over 1301 points, computed in C
    assert c_chain.angle_range_deg == numpy_chain.angle_range_deg
    np.testing.assert_allclose(c_chain.length_min_L0, numpy_chain.length_min_L0, rtol=0,
                               atol=1e-15)
    np.testing.assert_allclose(c_chain.length_max_L0, numpy_chain.length_max_L0, rtol=0,
                               atol=1e-15)
    with pytest.raises(ValueError, match="backend"):
        ChainConfig(backend="fortran")


def test_missing_compiler_is_a_clear_error(monkeypatch, tmp_path):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setenv("PROPRIO_C_CACHE", str(tmp_path))
    with pytest.raises(build.CBackendError, match=r"no C compiler.*backend='numpy'"):
        build.library_path("double")


def test_chebval_equals_numpy_and_configs_beyond_the_c_limits_are_refused():
    lib = native_chain.library("double")
    lib.ps_chebval.restype = ctypes.c_double
    lib.ps_chebval.argtypes = [ctypes.c_double, ctypes.POINTER(ctypes.c_double), ctypes.c_int]
    rng = np.random.default_rng(0)
    for n in (1, 2, 3, 7, 16):
        coef = rng.normal(size=n)
        for x in (-1.0, -0.3, 0.0, 0.77, 1.0):
            got = lib.ps_chebval(x, coef.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), n)
            assert got == pytest.approx(np.polynomial.chebyshev.chebval(x, coef), abs=1e-15)
    with pytest.raises(ValueError, match="PS_MEDIAN_MAX_WINDOW"):
        make_chain(ChainConfig(median_window=17, backend="c"))


def test_constants_match_the_header():
    """The binding's copies of the chain section's limits are the header's."""
    header = abi.header_constants()
    for name, value in (("PS_MEDIAN_MAX_WINDOW", native_chain.MEDIAN_MAX_WINDOW),
                        ("PS_FIT_MAX_COEFFS", native_chain.FIT_MAX_COEFFS),
                        ("PS_PREDICTOR_MAX_SEGMENTS", native_chain.PREDICTOR_MAX_SEGMENTS),
                        ("PS_CHAIN_MAX_UPDATES", native_chain.MAX_UPDATES),
                        ("PS_MUSCLES", len(MUSCLES))):
        assert header[name] == value, name


def test_status_enum_matches_the_header():
    """abi.Status has exactly the names and values of proprio.h's one enum ps_status."""
    assert {s.name: s.value for s in abi.Status} == abi.header_status_codes()
    assert "#define PS_ERR" not in build.HEADER.read_text()  # one enum, no stray defines
    assert abi.status_name(abi.Status.PS_ERR_INTERVAL) == "PS_ERR_INTERVAL"
    assert abi.status_name(99) == "unknown status 99"


def test_struct_layouts_match_the_header(tmp_path):
    """The ctypes mirrors have the C sizes and offsets (a compiled probe prints them)."""
    for variant in build.VARIANTS:
        s = native_chain.structs(variant)
        checks = [("ps_arm_chain", "PsArmChain", "state"), ("ps_chain_state", "PsChainState",
                  "last"), ("ps_chain_config", "PsChainConfig", "params"),
                  ("ps_chain_config", "PsChainConfig", "step_s"),
                  ("ps_arm_sample", "PsArmSample", "length_L0"),
                  ("ps_arm_sample", "PsArmSample", "ii_pps"),
                  ("ps_chain_state", "PsChainState", "counters"),
                  ("ps_predictor", "PsPredictor", "integral")]
        lines = "".join(
            f'printf("%lu %lu\\n", (unsigned long)sizeof({c}), '
            f'(unsigned long)offsetof({c}, {field}));\n' for c, _, field in checks)
        src = tmp_path / f"layout_{variant}.c"
        src.write_text('#include <stdio.h>\n#include <stddef.h>\n#include "proprio.h"\n'
                       f"int main(void) {{\n{lines}return 0;\n}}\n")
        exe = tmp_path / f"layout_{variant}"
        flags = ["-DPS_FLOAT"] if variant == "float" else []
        subprocess.run([*build.compiler_command(), *build.WARNING_FLAGS, *flags, "-I",
                        str(build.SOURCE_DIR), str(src), "-o", str(exe)], check=True)
        out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
        for (_, py, field), line in zip(checks, out.split("\n"), strict=False):
            size, offset = map(int, line.split())
            assert (ctypes.sizeof(s[py]), getattr(s[py], field).offset) == (size, offset), \
                (variant, py, field)


@pytest.mark.parametrize("variant", ["", "-DPS_FLOAT"])
def test_chain_compiles_warning_free_for_the_host_and_cortex_m0plus(tmp_path, variant):
    flags = [*build.WARNING_FLAGS, "-O2", *([variant] if variant else []), "-I",
             str(build.SOURCE_DIR), "-c"]
    for src in build.sources():
        subprocess.run([*build.compiler_command(), *flags, str(src), "-o",
                        str(tmp_path / (src.stem + ".o"))], check=True)
    cross = shutil.which("arm-none-eabi-gcc")
    if cross is None:
        pytest.skip("arm-none-eabi-gcc not installed (apt-get install gcc-arm-none-eabi)")
    for src in build.sources():
        subprocess.run([cross, *flags, "-mcpu=cortex-m0plus", "-mthumb", str(src), "-o",
                        str(tmp_path / (src.stem + ".arm.o"))], check=True)


# -- equivalence with the numpy chain ----------------------------------------------------------
def test_encoder_trace_run_chain_matches_numpy():
    """130 deg/s triangle through the noisy AX-12 model with 1 % invalid readings."""
    t_s, counts = encoder_trace(2.0, seed=0)
    ref = run_chain(t_s, counts=counts)
    got = run_chain(t_s, counts=counts, config=C)
    assert got.counters == ref.counters
    assert ref.counters["invalid_reading"] > 5 and ref.counters["accepted"] > 900
    for name, a in ref.columns().items():
        b = got.columns()[name]
        assert np.max(np.abs(a.astype(float) - b.astype(float))) <= TOL, name
    # the trace moves the whole chain: gamma_d switches, the spindles fire
    assert set(np.unique(ref.gamma_dynamic_pps)) == {0.0, 100.0}
    assert ref.ia_pps.max() > 50


def angle_events():
    """A 130 deg/s angle trace with every bad sample and the switch, as (kind, args)."""
    t, angle = triangle(1.4, dt=2e-3)
    events = []
    for i in range(1, t.size):
        ti, ai = t[i], angle[i]
        if i == 40:
            events += [("push_angle", (ti, math.nan)), ("push_angle", (ti, math.inf)),
                       ("push_angle", (ti, "bad"))]
        if i == 60:
            events += [("push_angle", (t[i - 1], ai)), ("push_angle", (t[i - 5], ai)),
                       ("push_angle", (math.nan, ai)), ("push_angle", (None, ai))]
        if i == 80:
            events.append(("set_intended_angle", (ai + 10.0,)))
        if i == 200:
            events.append(("set_intended_angle", (400.0,)))  # clamped to the range
        if i == 260:
            events.append(("set_intended_angle", (None,)))
        if 300 <= i < 330:
            continue  # dropped samples: a 60 ms gap
        if i == 400:
            ai = ai + 60.0  # a jump: slew-limited
        if 500 <= i < 560:
            ai = 200.0  # out of range: slew-limited towards it, then clamped
        if i == 600:  # a corrupt time 100 s ahead: a restart there, then a clock resync
            events.append(("push_angle", (ti + 100.0, ai)))
        events.append(("push_angle", (ti, ai)))
    return angle[0], events


def stream_both(events, reset_args, reset_kwargs=None, tol=TOL):
    numpy_chain, c_chain = pair()
    assert_same(numpy_chain.reset(*reset_args, **(reset_kwargs or {})),
                c_chain.reset(*reset_args, **(reset_kwargs or {})), "reset")
    for k, (kind, args) in enumerate(events):
        a = getattr(numpy_chain, kind)(*args)
        b = getattr(c_chain, kind)(*args)
        if kind == "set_intended_angle":
            continue
        assert_same(a, b, f"event {k} {kind}{args}", tol)
    assert c_chain.counters == numpy_chain.counters
    np.testing.assert_allclose(c_chain.spindle_state.tension_FU,
                               numpy_chain.spindle_state.tension_FU, rtol=0, atol=1e-9)
    return numpy_chain.counters


def test_angle_stream_with_bad_samples_gaps_and_the_switch_matches_numpy():
    angle0, events = angle_events()
    counters = stream_both(events, (angle0, 0.0))
    for name in COUNTERS:
        # (angle pushes carry no load word: the load rules are exercised with counts)
        if name not in ("invalid_reading", "invalid_length", "invalid_load", "missing_load"):
            assert counters[name] > 0, name  # every rule was exercised


def test_counts_stream_with_out_of_range_and_fractional_counts_matches_numpy():
    t_s, counts = encoder_trace(1.0, seed=3, invalid_rate=0.02)
    events = [("push_counts", (t, x)) for t, x in zip(t_s[1:], counts[1:], strict=True)]
    events[100:100] = [("push_counts", (t_s[101] - 1e-4, 500.5)),
                       ("push_counts", (t_s[101] - 1e-4, math.nan)),
                       ("push_counts", (t_s[101] - 1e-4, 1024)),
                       ("push_counts", (t_s[101] - 1e-4, -1)),
                       ("push_counts", (t_s[101] - 1e-4, "x"))]
    angle0 = float(ChainConfig().calibration.angle_deg(counts[0]))
    counters = stream_both(events, (angle0, t_s[0]))
    assert counters["invalid_reading"] >= 5


def test_length_stream_matches_numpy():
    fits = load_length_fits()
    t, angle = triangle(1.0, dt=2e-3)
    L = fits.length_L0(np.radians(angle))
    events = []
    for i in range(1, t.size):
        if i == 50:
            events += [("push_lengths", (t[i], [1.6, 1.0])), ("push_lengths", (t[i], [1.0])),
                       ("push_lengths", (t[i], [math.nan, 1.0])),
                       ("push_lengths", (t[i - 1], L[i]))]
        if 200 <= i < 215:
            continue
        events.append(("push_lengths", (t[i], L[i] + (0.3 if i == 300 else 0.0),
                                        angle[i] if i % 3 else None)))
    counters = stream_both(events, (angle[0], 0.0), {"length_L0": L[0]})
    assert counters["invalid_length"] == 3 and counters["gaps"] == 1
    assert counters["slew_limited"] >= 1


@pytest.mark.parametrize("config", [
    ChainConfig(method="backward_euler", lowpass_hz=None, median_window=3),
    ChainConfig(method="forward_euler", step_s=5e-4, max_gap_s=0.05),
    ChainConfig(lowpass_hz=8.0, step_s=3e-4),
])
def test_other_settings_match_numpy(config):
    t_s, counts = encoder_trace(0.4, seed=5)
    ref = run_chain(t_s, counts=counts, config=config)
    got = run_chain(t_s, counts=counts, config=replace(config, backend="c"))
    assert got.counters == ref.counters
    for name, a in ref.columns().items():
        assert np.max(np.abs(a.astype(float) - got.columns()[name].astype(float))) <= TOL, name


# -- blocks -------------------------------------------------------------------------------------
def test_block_pushes_equal_single_pushes_and_numpy_blocks():
    t_s, counts = encoder_trace(1.0, seed=1, invalid_rate=0.03)
    counts = counts.astype(float)
    t_s = t_s.copy()
    t_s[57] = t_s[56]  # a repeated time inside a block
    counts[123] = math.nan
    angle0 = float(ChainConfig().calibration.angle_deg(counts[0]))
    single, block, numpy_block = make_chain(C), make_chain(C), ArmChain(ChainConfig())
    for chain in (single, block, numpy_block):
        chain.reset(angle0, t_s[0])
    for start in range(1, t_s.size, 10):
        sl = slice(start, start + 10)
        for t, x in zip(t_s[sl], counts[sl], strict=True):
            single.push_counts(t, x)
        b = block.push_counts_block(t_s[sl], counts[sl])
        assert all(np.array_equal(getattr(b, f.name), getattr(single.last, f.name))
                   for f in fields(ArmSample))  # bit for bit
        assert_same(numpy_block.push_counts_block(t_s[sl], counts[sl]), b, f"block {start}")
    assert block.counters == single.counters == numpy_block.counters
    # the other two block pushes, against numpy's
    fits = load_length_fits()
    t, angle = triangle(0.3, dt=2e-3)
    for kind, signal in (("push_angle_block", angle),
                         ("push_lengths_block", fits.length_L0(np.radians(angle)))):
        a, b = pair()
        kwargs = {"length_L0": signal[0]} if kind == "push_lengths_block" else {}
        a.reset(angle[0], 0.0, **kwargs)
        b.reset(angle[0], 0.0, **kwargs)
        for start in range(1, t.size, 10):
            sl = slice(start, start + 10)
            assert_same(getattr(a, kind)(t[sl], signal[sl]), getattr(b, kind)(t[sl], signal[sl]),
                        f"{kind} {start}")
        assert a.counters == b.counters
    with pytest.raises(ValueError, match="shape"):
        block.push_lengths_block(np.zeros(3), np.zeros((3, 3)))


# -- errors leave the chain unchanged --------------------------------------------------------
def test_errors_are_clear_and_leave_the_chain_unchanged():
    chain = make_chain(C)
    with pytest.raises(RuntimeError, match="reset"):
        chain.push_angle(0.1, 30.0)
    assert chain.reset(140.0).angle_deg == pytest.approx(130.0)  # clamped, as numpy's
    assert chain.counters["angle_clamped"] == 1
    with pytest.raises(ValueError, match="finite"):
        chain.reset(30.0, math.nan)
    with pytest.raises(ValueError, match="length_L0"):
        chain.reset(30.0, 0.0, length_L0=[0.2, 1.0])
    chain.reset(30.0, 0.0)
    chain.push_angle(0.002, 30.5)
    with pytest.raises(ValueError, match="finite"):
        chain.set_intended_angle(math.nan)
    before, counters = chain.last, chain.counters
    state = chain.spindle_state
    params = chain._chain.config.params
    saved = params.M[0]
    params.M[0] = math.nan  # an injected fault: the next spindle step fails
    with pytest.raises(FloatingPointError, match="unchanged"):
        chain.push_angle(0.03, 40.0)
    params.M[0] = saved
    assert chain.counters == counters
    assert all(np.array_equal(getattr(chain.last, f.name), getattr(before, f.name))
               for f in fields(ArmSample))
    np.testing.assert_array_equal(chain.spindle_state.tension_FU, state.tension_FU)
    out = chain.push_angle(0.004, 31.0)  # and it carries on
    assert out.accepted and chain.counters["accepted"] == 2
    # a corrupt clock restarts the chain at rest there, in bounded time (tests/
    # test_chain_faults.py checks the rule)
    assert chain.push_angle(1e12, 40.0).accepted and chain.counters["restarts"] == 1
    assert chain.push_angle_block(np.array([1e300]), np.array([40.0])).t_s == 1e300


# -- the float build ----------------------------------------------------------------------------
FLOAT_TOL = {"angle_deg": 1e-4, "length_L0": 2e-6, "velocity_L0_s": 1e-4, "template_L0": 2e-6,
             "gamma_static_pps": 5e-4, "ia_pps": 0.01, "ii_pps": 0.005}
"""Float-vs-double bounds: about 5x the largest deviation measured on 3 s encoder traces
(docs/c_chain.md: Ia 0.0016 pps, II 0.0008 pps, length 4e-7 L0)."""


def float_deviation(duration_s=2.0, seed=0):
    t_s, counts = encoder_trace(duration_s, seed=seed)
    ref = run_chain(t_s, counts=counts, config=C)
    chain = native_chain.CArmChain(ChainConfig(), variant="float")
    chain.reset(float(chain.config.calibration.angle_deg(counts[0])), t_s[0])
    outs = [chain.last] + [chain.push_counts(t, x) for t, x in zip(t_s[1:], counts[1:],
                                                                    strict=True)]
    dev = {name: float(np.max(np.abs(getattr(ref, name) - np.array(
        [getattr(o, name) for o in outs])))) for name in FLOAT_TOL}
    gd_flips = int(np.sum(ref.gamma_dynamic_pps != np.array([o.gamma_dynamic_pps for o in outs])))
    return dev, gd_flips, ref.counters == chain.counters


def test_float_build_stays_within_its_documented_tolerance():
    dev, gd_flips, same_counters = float_deviation()
    assert same_counters
    assert gd_flips == 0  # g(x)'s threshold decision is the same at every sample
    for name, tol in FLOAT_TOL.items():
        assert dev[name] <= tol, (name, dev[name])


def test_float_build_counts_an_interval_below_flt_min_as_a_repeated_time():
    """docs/faults.md: in the float build a time less than FLT_MIN after the last accepted one
    is a repeated time (its interval would be a zero or denormal float step); the double
    build accepts it."""
    flt_min = float(np.finfo(np.float32).tiny)
    for variant, accepted in (("float", False), ("double", True)):
        chain = native_chain.CArmChain(ChainConfig(), variant=variant)
        chain.reset(40.0, 0.0)
        out = chain.push_angle(flt_min / 2, 40.5)
        assert out.accepted is accepted, variant
        assert chain.counters["repeated_time"] == (0 if accepted else 1), variant
        assert chain.push_angle(2e-3, 41.0).accepted, variant  # and the chain goes on


# -- the C-only path a microcontroller build takes -----------------------------------------------
DEVICE_MAIN = r"""
#include <stdio.h>
#include "proprio.h"
extern const ps_chain_config proprio_chain_config;
int main(void) {
    static ps_arm_chain chain; /* static: no large stack frame, as on a device */
    ps_arm_sample out;
    double t, counts, angle0;
    if (ps_chain_init(&chain, &proprio_chain_config) != PS_OK) return 3;
    if (scanf("%lf %lf", &t, &angle0) != 2) return 4;
    if (ps_chain_reset(&chain, (ps_real)angle0, t, NULL, &out) != PS_OK) return 5;
    while (scanf("%lf %lf", &t, &counts) == 2) {
        if (ps_chain_push_counts(&chain, t, (ps_real)counts, &out) != PS_OK) return 6;
        printf("%d %.17g %.17g %.17g %.17g\n", out.accepted, (double)out.ia_pps[0],
               (double)out.ia_pps[1], (double)out.ii_pps[0], (double)out.ii_pps[1]);
    }
    return 0;
}
"""


@pytest.mark.parametrize("variant", build.VARIANTS)
def test_generated_config_source_runs_the_chain_in_plain_c(tmp_path, variant):
    """config_c_source + spindle/native/c/*.c + a main reading counts: the numpy chain's rates."""
    (tmp_path / "config.c").write_text(native_chain.config_c_source())
    (tmp_path / "main.c").write_text(DEVICE_MAIN)
    exe = tmp_path / "device"
    flags = ["-DPS_FLOAT"] if variant == "float" else []
    subprocess.run([*build.compiler_command(), *build.WARNING_FLAGS, "-O2", *flags, "-I",
                    str(build.SOURCE_DIR), *map(str, build.sources()),
                    str(tmp_path / "config.c"), str(tmp_path / "main.c"), "-o", str(exe), "-lm"],
                   check=True)
    t_s, counts = encoder_trace(1.0, seed=2)
    angle0 = float(ChainConfig().calibration.angle_deg(counts[0]))
    stdin = f"{float(t_s[0])!r} {angle0!r}\n" + "".join(
        f"{float(t)!r} {int(x)}\n" for t, x in zip(t_s[1:], counts[1:], strict=True))
    result = subprocess.run([str(exe)], input=stdin, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    got = np.loadtxt(result.stdout.splitlines())
    ref = run_chain(t_s, counts=counts)
    np.testing.assert_array_equal(got[:, 0], ref.accepted[1:])
    tol = TOL if variant == "double" else FLOAT_TOL["ia_pps"]
    np.testing.assert_allclose(got[:, 1:3], ref.ia_pps[1:], rtol=0, atol=tol)
    np.testing.assert_allclose(got[:, 3:5], ref.ii_pps[1:], rtol=0, atol=tol)


def test_run_chain_in_one_c_call_with_the_switch_and_a_bad_start_matches_numpy():
    t, angle = triangle(1.2, dt=2e-3)
    angle = angle.copy()
    angle[:3] = math.nan  # the chain starts at the first valid sample
    angle[200] = math.inf
    intended = np.full(t.size, math.nan)
    intended[100:300] = 120.0
    intended[350:360] = -30.0  # clamped
    t = t.copy()
    t[250] = t[249]
    ref = run_chain(t, angle_deg=angle, intended_angle_deg=intended)
    got = run_chain(t, angle_deg=angle, intended_angle_deg=intended, config=C)
    assert got.counters == ref.counters and ref.counters["invalid_angle"] == 1
    for name, a in ref.columns().items():
        assert np.max(np.abs(a.astype(float) - got.columns()[name].astype(float))) <= TOL, name
    # the switch moved the template: gamma_s differs from the measured-motion run
    plain = run_chain(t, angle_deg=angle, config=C)
    assert np.max(np.abs(plain.template_L0 - got.template_L0)) > 0.05
    # lengths too
    L = load_length_fits().length_L0(np.radians(np.nan_to_num(angle, nan=40.0, posinf=40.0)))
    ref = run_chain(t, length_L0=L, intended_angle_deg=intended)
    got = run_chain(t, length_L0=L, intended_angle_deg=intended, config=C)
    assert got.counters == ref.counters
    for name, a in ref.columns().items():
        assert np.max(np.abs(a.astype(float) - got.columns()[name].astype(float))) <= TOL, name
    intended[400] = math.inf
    for config in (ChainConfig(), C):
        with pytest.raises(ValueError, match="finite"):
            run_chain(t, angle_deg=angle, intended_angle_deg=intended, config=config)


def test_run_trace_equals_single_pushes_bit_for_bit():
    t_s, counts = encoder_trace(0.5, seed=4, invalid_rate=0.05)
    angle0 = float(ChainConfig().calibration.angle_deg(counts[0]))
    single, whole = make_chain(C), make_chain(C)
    single.reset(angle0, t_s[0])
    whole.reset(angle0, t_s[0])
    outs = [single.push_counts(t, x) for t, x in zip(t_s[1:], counts[1:], strict=True)]
    table = whole.run_trace("push_counts", t_s[1:], counts[1:])
    for f in fields(ArmSample):
        np.testing.assert_array_equal(table[f.name], [getattr(o, f.name) for o in outs])
    assert whole.counters == single.counters
    assert all(np.array_equal(getattr(whole.last, f.name), getattr(single.last, f.name))
               for f in fields(ArmSample))
