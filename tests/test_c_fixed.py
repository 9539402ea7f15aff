"""The fixed-point spindle step (ps_spindle_step_fx, int32 Q24) against the double C step.

The fixed-point step is plain C99, so it is compiled for the host (the cached library of
spindle.native.build) and compared with the double ``ps_spindle_step`` (itself equal to the numpy
core to ~1e-12 pps, tests/test_c_spindle.py) at the same step and theta, on the Mileusnic
Fig. 3 protocol and on random trajectories over the valid input range. What is left is the
fixed-point arithmetic (Q24 resolution 6e-8, products rounded to nearest, Newton to 1e-4 in
z). Measured maxima of |dIa|, |dII|: HUMAN 0.0016 / 0.0037 pps on Fig. 3 at 5 / 1 ms, 0.0006
pps on the random trajectories at 5 and 2 ms; CAT (5x the gains) 0.0082 / 0.019 and 0.0031
pps. Documented tolerance: 0.02 pps x (bag1 G_pri / 4000
pps/L0), i.e. 0.02 pps for HUMAN and 0.1 pps for CAT (~5x the measured maxima). The
Cortex-M0+ build computes the same integers as this host build (spindle.native.m0plus, run by
scripts/bench_embedded.py: emulator vs host 0 pps).

The sanitizer fuzz (spindle/native/c/fuzz/fuzz_fixed.c, ASan + UBSan, which abort on any signed
int32 overflow) checks the overflow guarantee of ps_plan_fx_init's bound analysis on random
and perturbed constants, in-range and corrupted states and invalid inputs, and the status
codes and the untouched state on failure.
"""

from __future__ import annotations

import ctypes
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from c_layout import c_layout
from sanitized_build import SANITIZER_REPORT, build

import spindle
from spindle.native import abi, fixed
from spindle.native import build as native_build
from spindle.native.abi import Status

try:
    native_build.find_compiler()
except native_build.CBackendError as exc:  # pragma: no cover - depends on the machine
    pytest.skip(str(exc), allow_module_level=True)

PRESETS = {"HUMAN": spindle.HUMAN, "CAT": spindle.CAT}
SPEEDS = (0.11, 0.66, 1.55)
DRIVES = ((0.0, 0.0), (70.0, 0.0), (0.0, 70.0))
PS_OK = Status.PS_OK
PS_ERR_NULL = Status.PS_ERR_NULL
PS_ERR_NONFINITE = Status.PS_ERR_NONFINITE
PS_ERR_LENGTH_RANGE = Status.PS_ERR_LENGTH_RANGE
PS_ERR_NEGATIVE_DRIVE = Status.PS_ERR_NEGATIVE_DRIVE
PS_ERR_STEP = Status.PS_ERR_STEP
PS_ERR_SPEED = Status.PS_ERR_SPEED
PS_ERR_METHOD = Status.PS_ERR_METHOD
PS_ERR_CONFIG = Status.PS_ERR_CONFIG


def tolerance_pps(params) -> float:
    return 0.02 * params.bag1.G_primary_pps_L0 / 4000.0


@pytest.fixture(scope="module")
def lib() -> ctypes.CDLL:
    out = native_build.load("double")
    fixed.declare_fixed(out, "double")
    _, PsSpindle = abi.structs("double")
    PsParams, _ = abi.structs("double")
    P, d = ctypes.POINTER, ctypes.c_double
    out.ps_spindle_init.argtypes = [P(PsSpindle), P(PsParams), d, d, d]
    out.ps_spindle_step.argtypes = [P(PsSpindle), P(PsParams), d, d, d, d, d, P(d), P(d)]
    out.ps_spindle_afferents.argtypes = [P(PsSpindle), P(PsParams), P(d), P(d)]
    out.ps_spindle_afferents.restype = None
    return out


def test_q_scales_and_layouts_match_the_header(tmp_path):
    """The binding's Q scales and ps_plan_fx / ps_spindle_fx mirrors are the header's."""
    header = abi.header_constants()
    assert (header["PS_FX_ONE"], header["PS_FX_DRIVE_ONE"], header["PS_FX_RATE_ONE"],
            header["PS_FX_ROOT_TABLE"]) == (fixed.FX_Q24, fixed.FX_DRIVE, fixed.FX_RATE,
                                            abi.FX_ROOT_TABLE)
    PsPlanFx, PsSpindleFx = abi.fixed_structs()
    checks = [("ps_plan_fx", PsPlanFx, "dg_shift"), ("ps_plan_fx", PsPlanFx, "fibre"),
              ("ps_plan_fx", PsPlanFx, "root10"), ("ps_spindle_fx", PsSpindleFx, "target"),
              ("ps_spindle_fx", PsSpindleFx, "gs")]
    got = [(ctypes.sizeof(py), getattr(py, field).offset) for _, py, field in checks]
    assert got == c_layout([(c, field) for c, _, field in checks], tmp_path)


def make_plan(lib, params, h: float, theta: float = 0.5):
    PsPlanFx, _ = abi.fixed_structs()
    plan = PsPlanFx()
    code = lib.ps_plan_fx_init(ctypes.byref(plan),
                               ctypes.byref(abi.params_struct(params, "double")), h, theta)
    assert code == PS_OK
    return plan


def double_rates(lib, params, L, gd, gs, h: float, theta: float = 0.5):
    """The double ps_spindle_step along the same samples; (ia, ii, status)."""
    _, PsSpindle = abi.structs("double")
    p = abi.params_struct(params, "double")
    s = PsSpindle()
    ia = np.full(len(L), np.nan)
    ii = np.full(len(L), np.nan)
    code = lib.ps_spindle_init(ctypes.byref(s), ctypes.byref(p), L[0], gd[0], gs[0])
    if code != PS_OK:
        return ia, ii, code
    a, b = ctypes.c_double(), ctypes.c_double()
    lib.ps_spindle_afferents(ctypes.byref(s), ctypes.byref(p), ctypes.byref(a), ctypes.byref(b))
    ia[0], ii[0] = a.value, b.value
    for j in range(1, len(L)):
        code = lib.ps_spindle_step(ctypes.byref(s), ctypes.byref(p), L[j], gd[j], gs[j], h,
                                   theta, ctypes.byref(a), ctypes.byref(b))
        if code != PS_OK:
            return ia, ii, code
        ia[j], ii[j] = a.value, b.value
    return ia, ii, PS_OK


def as_q(L, gd, gs):
    """The samples as the fixed-point step sees them (Q24 lengths, Q8 drives)."""
    return (np.round(L * fixed.FX_Q24) / fixed.FX_Q24, np.round(gd * fixed.FX_DRIVE)
            / fixed.FX_DRIVE, np.round(gs * fixed.FX_DRIVE) / fixed.FX_DRIVE)


def compare(lib, params, L, gd, gs, h, theta=0.5) -> float:
    L, gd, gs = as_q(np.asarray(L, float), np.broadcast_to(gd, np.shape(L)).astype(float),
                     np.broadcast_to(gs, np.shape(L)).astype(float))
    fia, fii, fcode = fixed.fixed_rates(lib, make_plan(lib, params, h, theta), L, gd, gs)
    dia, dii, dcode = double_rates(lib, params, L, gd, gs, h, theta)
    assert fcode == PS_OK and dcode == PS_OK
    return float(max(np.max(np.abs(fia - dia)), np.max(np.abs(fii - dii))))


def fig3_length(speed: float, h: float) -> np.ndarray:
    t = np.arange(round(3.3 / h) + 1) * h
    return 0.95 + speed * np.clip(t - 1.0, 0.0, (1.08 - 0.95) / speed)


@pytest.mark.parametrize("preset", list(PRESETS))
@pytest.mark.parametrize("h", [5e-3, 1e-3])
def test_fig3_matches_double_step(lib, preset, h):
    params = PRESETS[preset]
    worst = max(compare(lib, params, fig3_length(v, h), gd, gs, h)
                for v in SPEEDS for gd, gs in DRIVES)
    assert worst <= tolerance_pps(params), worst


def test_fig3_backward_euler(lib):
    worst = max(compare(lib, spindle.HUMAN, fig3_length(v, 5e-3), 70.0, 0.0, 5e-3, theta=1.0)
                for v in SPEEDS)
    assert worst <= tolerance_pps(spindle.HUMAN), worst


def random_trajectory(rng, h: float, duration_s: float = 2.0):
    """A smooth length over most of [0.5, 1.5] L0 (|dL/dt| up to ~8 L0/s) and stepwise random
    drives in [0, 300] pps."""
    t = np.arange(round(duration_s / h) + 1) * h
    freq = rng.uniform(0.3, 4.0, size=4)
    amp = rng.uniform(0.0, 0.08, size=4)
    phase = rng.uniform(0, 2 * np.pi, size=4)
    L = rng.uniform(0.75, 1.25) + (amp * np.sin(2 * np.pi * freq * t[:, None] + phase)).sum(1)
    L = np.clip(L, 0.55, 1.45)
    hold = max(1, round(rng.uniform(0.05, 0.5) / h))
    gd = np.repeat(rng.uniform(0, 300, len(t) // hold + 1), hold)[:len(t)]
    gs = np.repeat(rng.uniform(0, 300, len(t) // hold + 1), hold)[:len(t)]
    return L, gd, gs


@pytest.mark.parametrize("preset", list(PRESETS))
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_random_trajectories_match_double_step(lib, preset, seed):
    rng = np.random.default_rng(seed)
    params = PRESETS[preset]
    for h in (5e-3, 2e-3):
        for _ in range(3):
            L, gd, gs = random_trajectory(rng, h)
            assert np.max(np.abs(np.diff(L))) / h <= 10.0
            worst = compare(lib, params, L, gd, gs, h)
            assert worst <= tolerance_pps(params), (h, worst)


def test_accuracy_against_stiff_reference(lib):
    """Fig. 3 at 5 ms (HUMAN): within the embedded target of 2 pps RMS against scipy Radau,
    and no worse than the double step at the same step by more than 0.01 pps."""
    pytest.importorskip("scipy")
    from spindle.reference import PUBLISHED_HUMAN, ramp_and_hold, solve_reference

    h = 5e-3
    t = np.arange(round(3.3 / h) + 1) * h
    plan = make_plan(lib, spindle.HUMAN, h)
    for v in (0.66, 1.55):
        for gd, gs in DRIVES:
            L, dgd, dgs = as_q(fig3_length(v, h), np.full(len(t), gd), np.full(len(t), gs))
            ia, ii, code = fixed.fixed_rates(lib, plan, L, dgd, dgs)
            assert code == PS_OK
            dia, dii, _ = double_rates(lib, spindle.HUMAN, L, dgd, dgs, h)
            ref = solve_reference(ramp_and_hold(speed_L0_s=v, gamma_dyn_pps=gd,
                                                gamma_stat_pps=gs), t, params=PUBLISHED_HUMAN)
            for got, dbl, r in ((ia, dia, ref.ia), (ii, dii, ref.ii)):
                rms = np.sqrt(np.mean((got - r) ** 2))
                assert rms <= 2.0
                assert rms <= np.sqrt(np.mean((dbl - r) ** 2)) + 0.01


def test_status_codes_and_untouched_state(lib):
    _, PsSpindleFx = abi.fixed_structs()
    plan = make_plan(lib, spindle.HUMAN, 5e-3)
    one = fixed.FX_Q24
    s = PsSpindleFx()
    assert lib.ps_spindle_fx_init(ctypes.byref(s), ctypes.byref(plan), one, 0, 0) == PS_OK
    before = bytes(s)
    a, b = ctypes.c_int32(123), ctypes.c_int32(456)
    cases = [(one // 2 - 1, 0, 0, PS_ERR_LENGTH_RANGE), (one * 3 // 2 + 1, 0, 0,
             PS_ERR_LENGTH_RANGE), (one, -1, 0, PS_ERR_NEGATIVE_DRIVE),
             (one, 0, -5, PS_ERR_NEGATIVE_DRIVE), (one + one // 10, 0, 0, PS_ERR_SPEED)]
    for L, gd, gs, want in cases:
        got = lib.ps_spindle_step_fx(ctypes.byref(s), ctypes.byref(plan), L, gd, gs,
                                     ctypes.byref(a), ctypes.byref(b))
        assert got == want
        assert bytes(s) == before and (a.value, b.value) == (123, 456)
    assert lib.ps_spindle_step_fx(None, ctypes.byref(plan), one, 0, 0, None, None) == PS_ERR_NULL
    assert lib.ps_spindle_step_fx(ctypes.byref(s), None, one, 0, 0, None, None) == PS_ERR_NULL
    # a corrupted state (tension beyond its Q range) is refused, not stepped
    s.T[1] = 9 * one
    corrupted = bytes(s)
    assert lib.ps_spindle_step_fx(ctypes.byref(s), ctypes.byref(plan), one, 0, 0, None,
                                  None) == PS_ERR_NONFINITE
    assert bytes(s) == corrupted
    # a drive far above 300 pps saturates the activation target instead of overflowing
    s = PsSpindleFx()
    assert lib.ps_spindle_fx_init(ctypes.byref(s), ctypes.byref(plan), one, 2**31 - 1,
                                  2**31 - 1) == PS_OK
    assert all(0.99 * one <= s.f[i] <= one for i in range(3))


def test_plan_refuses_what_it_cannot_represent(lib):
    PsPlanFx, _ = abi.fixed_structs()
    plan = PsPlanFx()

    def init(params, h=5e-3, theta=0.5):
        return lib.ps_plan_fx_init(ctypes.byref(plan),
                                   ctypes.byref(abi.params_struct(params, "double")), h,
                                   theta)

    assert init(spindle.HUMAN, theta=0.0) == PS_ERR_METHOD  # explicit: not in fixed point
    assert init(spindle.HUMAN, theta=1.5) == PS_ERR_METHOD
    assert init(spindle.HUMAN, h=0.0) == PS_ERR_STEP
    assert init(spindle.HUMAN, h=float("nan")) == PS_ERR_STEP
    assert init(spindle.CAT.scale_gains(10.0)) == PS_ERR_CONFIG  # rates beyond 32767 pps
    assert init(spindle.HUMAN, h=0.5) == PS_ERR_CONFIG  # KSR*dL bounds beyond the Q range
    assert lib.ps_plan_fx_init(None, None, 5e-3, 0.5) == PS_ERR_NULL


# ---- sanitizer fuzz (spindle/native/c/fuzz/fuzz_fixed.c) -----------------------------------------

FUZZ_SOURCE = native_build.SOURCE_DIR / "fuzz" / "fuzz_fixed.c"


@pytest.fixture(scope="module")
def fuzzers(tmp_path_factory) -> dict[str, Path]:
    """fuzz_fixed.c + spindle.c under ASan + UBSan, ps_real double and float."""
    if not FUZZ_SOURCE.exists():  # pragma: no cover - an installed wheel
        pytest.skip(f"{FUZZ_SOURCE} not found (run the tests from a source checkout)")
    root = tmp_path_factory.mktemp("fuzz_fixed")
    out = {}
    for variant in native_build.VARIANTS:
        out[variant] = build(root / f"fuzz_fixed_{variant}",
                             [native_build.SOURCE_DIR / "spindle.c", FUZZ_SOURCE], variant)
    return out


def run_fuzzer(binary: Path, seed: int, iterations: int) -> dict[str, int]:
    result = subprocess.run([str(binary), str(seed), str(iterations)], capture_output=True,
                            text=True, timeout=900)
    report = result.stdout + result.stderr
    assert result.returncode == 0, report[-3000:]
    assert not SANITIZER_REPORT.search(report), report[-3000:]
    counts = {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", result.stdout)}
    assert counts["iterations"] == iterations
    # accepted plans, accepted steps and refused ones all exercised
    assert counts["plans"] > iterations // 2
    assert counts["ok"] > iterations // 10 and counts["refused"] > iterations // 10
    return counts


@pytest.mark.parametrize("variant", native_build.VARIANTS)
def test_fixed_sanitizer_smoke(fuzzers, variant):
    run_fuzzer(fuzzers[variant], seed=1, iterations=50_000)


@pytest.mark.slow
@pytest.mark.parametrize("variant", native_build.VARIANTS)
@pytest.mark.parametrize("seed", [2, 3, 4, 5])
def test_fixed_sanitizer_long_random_runs(fuzzers, variant, seed):
    run_fuzzer(fuzzers[variant], seed=seed, iterations=1_000_000)


def extreme_trajectory(rng, h: float, duration_s: float = 2.0):
    """Moves at the speed limit (9.99 L0/s) between random lengths near both ends of the
    range, with drives up to 300 pps: where |v| reaches ~40 L0/s and |T| ~1.6 in the double
    step (the largest values of the fixed-point ranges' design)."""
    n = round(duration_s / h) + 1
    t = np.arange(n) * h
    high = np.sin(2 * np.pi * rng.uniform(0.5, 3.0) * t + rng.uniform(0, 6)) > 0
    target = np.where(high, rng.uniform(1.1, 1.5), rng.uniform(0.5, 0.9))
    L = np.empty(n)
    L[0] = 1.0
    for j in range(1, n):
        L[j] = L[j - 1] + np.clip(target[j] - L[j - 1], -9.99 * h, 9.99 * h)
    gd = np.repeat(rng.uniform(0, 300, n // 50 + 1), 50)[:n]
    gs = np.repeat(rng.uniform(0, 300, n // 50 + 1), 50)[:n]
    return L, gd, gs


@pytest.mark.parametrize("preset", list(PRESETS))
@pytest.mark.parametrize("h", [5e-3, 1e-3])
def test_speed_limit_moves_match_double_step(lib, preset, h):
    """Documented tolerance at the edge of the input range: 2.5x the general one (measured
    0.025 / 0.013 pps HUMAN, 0.12 / 0.066 pps CAT at 5 / 1 ms)."""
    rng = np.random.default_rng(5)
    params = PRESETS[preset]
    worst = max(compare(lib, params, *extreme_trajectory(rng, h), h) for _ in range(6))
    assert worst <= 2.5 * tolerance_pps(params), worst
