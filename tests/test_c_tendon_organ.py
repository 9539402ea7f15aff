"""The C tendon organ (double and fixed point) against the numpy step and the reference."""

from __future__ import annotations

import ctypes
import re
import subprocess
import sys

import numpy as np
import pytest

from spindle import tendon_organ as gto
from spindle.backends import resolve_backend
from spindle.native import abi, build
from spindle.native import tendon_organ as cgto
from spindle.tendon_organ_params import (
    ARM26_MAX_ISOMETRIC_FORCE_N,
    CAT,
    HUMAN,
    MAX_FORCE_N,
    force_scales_N,
    static_rate_pps,
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


def log1p_points() -> np.ndarray:
    """x >= 0 over the whole double range: log-uniform 1e-320 .. 1e308, uniform 0 .. 4, the
    reduction's edges 2^k sqrt(1/2) - 1 and 2^k - 1 (k = 0 .. 1023) with their neighbours,
    and 0, the smallest subnormal and normal, 2^-53 and the largest double."""
    rng = np.random.default_rng(5)
    k = np.arange(0, 1024)
    with np.errstate(over="ignore"):
        edges = np.concatenate([np.ldexp(np.sqrt(0.5), k) - 1.0, np.ldexp(1.0, k) - 1.0])
        near = np.concatenate([np.nextafter(edges, np.inf), np.nextafter(edges, 0), edges])
    x = np.concatenate([10.0 ** rng.uniform(-320, 308, 100_000), rng.uniform(0, 4, 50_000), near,
                        [0.0, 5e-324, np.finfo(float).tiny, 2.0**-53, np.finfo(float).max]])
    return x[(x >= 0) & np.isfinite(x)]


@pytest.mark.skipif(np.finfo(np.longdouble).nmant < 63, reason="needs x87 long double")
def test_own_log1p_within_one_ulp_over_the_whole_range():
    """ps_gto_log1p (the double build's inline log1p of the log stage and the SIMD lanes)
    against numpy's long-double log1p (64-bit mantissa: 2^11 finer than a double's ulp) on
    156,147 points (:func:`log1p_points`). Measured: max 0.749 ulp, mean 0.176; libm's log1p
    on the same points 0.566, mean 0.173."""
    lib = cgto.library()
    x = log1p_points()
    y = np.array([lib.ps_gto_log1p(v) for v in x.tolist()])
    ref = np.log1p(x.astype(np.longdouble))
    ulps = np.abs((y.astype(np.longdouble) - ref) / np.spacing(ref.astype(np.float64)))
    assert float(ulps.max()) < 0.8
    assert lib.ps_gto_log1p(0.0) == 0.0 and lib.ps_gto_log1p(5e-324) == 5e-324
    assert lib.ps_gto_log1p(np.inf) == np.inf


def test_log1p_constants_are_the_fit_scripts():
    """The #defines of gto_log1p (ln 2 split, Q's coefficients) are what
    scripts/fit_log1p.py prints."""
    pytest.importorskip("mpmath")
    script = build.SOURCE_DIR.parents[2] / "scripts" / "fit_log1p.py"
    printed = subprocess.run([sys.executable, str(script)], check=True, capture_output=True,
                             text=True).stdout
    want = dict(re.findall(r"#define (GTO_\w+) (\S+)", printed))
    source = (build.SOURCE_DIR / "tendon_organ.c").read_text()
    have = dict(re.findall(r"#define (GTO_LN2_\w+|GTO_LOG_Q\d) (\S+)", source))
    assert len(want) == 9 and have == want


def lanes_forces(n: int, steps: int) -> np.ndarray:
    """Random-walk forces with a slack sample, and in two organs a jump (0 -> 5 kN: ln cosh
    off its series, the lanes' scalar fix-up) inside a block of lanes and in the tail."""
    f = random_forces(3, (steps, n), 25.0)
    f[9, 3] = 0.0
    f[10, 3] = 5000.0
    f[20, n - 1] = 5000.0
    return np.ascontiguousarray(f)


def scalar_steps(lib: ctypes.CDLL, states: ctypes.Array, plan: cgto.PsGtoPlan,
                 f: np.ndarray, g: np.ndarray) -> np.ndarray:
    ib, out = ctypes.c_double(), np.empty(f.shape)
    for k in range(f.shape[0]):
        for i in range(f.shape[1]):
            assert lib.ps_gto_step(ctypes.byref(states[i]), ctypes.byref(plan), f[k, i], g[i],
                                   ctypes.byref(ib)) == abi.Status.PS_OK
            out[k, i] = ib.value
    return out


@pytest.mark.parametrize("defines", [(), ("-DPS_GTO_LANES_NO_AVX512",),
                                     ("-DPS_GTO_LANES_NO_AVX2",), ("-DPS_GTO_BATCH_SCALAR",)])
def test_batch_lanes_equal_the_scalar_step_in_every_build(tmp_path, defines):
    """ps_gto_batch_run (SIMD lanes of 8 organs: the best of AVX-512 / AVX2 the CPU has, AVX2
    at most, the baseline instruction set, none) equals ps_gto_step organ by organ, bit for
    bit: rates and states, over 40 steps (more than one chunk of logs) of 21 organs (two
    blocks and a tail of 5), jumps included; and every build equals the shipped library."""
    out = tmp_path / "libgto.so"
    cmd = [*build.compiler_command(), *build.compile_flags("double"), *defines, "-I",
           str(build.SOURCE_DIR), str(build.SOURCE_DIR / "tendon_organ.c"), "-o", str(out),
           "-lm"]
    subprocess.run(cmd, check=True, capture_output=True)
    lib = ctypes.CDLL(str(out))
    for name, types in (("ps_gto_step", [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_double,
                                         ctypes.c_double, ctypes.c_void_p]),
                        ("ps_gto_batch_run", cgto.library().ps_gto_batch_run.argtypes)):
        getattr(lib, name).argtypes = types
    n, steps = 21, 40
    f = lanes_forces(n, steps)
    g = np.linspace(4.0, 400.0, n)
    shipped = cgto.CTendonOrgans(g, HUMAN, 1e-3, force_N=f[0])
    start = bytes(shipped._states)
    lanes = (cgto.PsGto * n).from_buffer_copy(start)
    scalar = (cgto.PsGto * n).from_buffer_copy(start)
    ib = np.empty((steps - 1, n))
    assert lib.ps_gto_batch_run(ctypes.addressof(lanes), n, ctypes.byref(shipped.plan),
                                steps - 1, f[1:].ctypes.data, g.ctypes.data, ib.ctypes.data,
                                None) == abi.Status.PS_OK
    want = scalar_steps(lib, scalar, shipped.plan, f[1:], g)
    np.testing.assert_array_equal(ib, want)
    assert bytes(lanes) == bytes(scalar)
    np.testing.assert_array_equal(shipped.run(f[1:]), want)
    assert bytes(shipped._states) == bytes(scalar)


@pytest.mark.parametrize("bad", [np.nan, -np.inf, np.inf, 2 * MAX_FORCE_N])
@pytest.mark.parametrize("where", [(0, 0), (17, 5), (30, 19), (38, 20)])
def test_batch_finds_the_first_bad_force_anywhere_and_writes_nothing(bad, where):
    """The one vectorised pass over every force (in blocks of 8 and the tail) refuses what
    check_force refuses and then names the first bad force in step order; MAX_FORCE_N itself
    and any finite negative force pass."""
    n, steps = 21, 39
    f = lanes_forces(n, steps + 1)[1:]
    f[2, 4], f[3, 8] = MAX_FORCE_N, -1e300
    organs = cgto.CTendonOrgans(np.full(n, 50.0), HUMAN, 1e-3)
    before = bytes(organs._states)
    organs.run(f)
    organs._states = (cgto.PsGto * n).from_buffer_copy(before)
    if where != (steps - 1, n - 1):
        f[steps - 1, n - 1] = np.nan  # a later bad force, not the one reported
    f[where] = bad
    index = where[0] * n + where[1]
    with pytest.raises(ValueError, match=rf"force_N=.* \(flat index {index}\)"):
        organs.run(f)
    assert bytes(organs._states) == before


def test_status_code_of_the_force_range_is_in_the_header():
    assert abi.header_status_codes()["PS_ERR_FORCE_RANGE"] == abi.Status.PS_ERR_FORCE_RANGE
    consts = abi.header_constants()
    assert consts["PS_GTO_MAX_FORCE_N"] == MAX_FORCE_N
    assert consts["PS_GTO_MAX_STEP_S"] == gto.MAX_STEP_S
    assert consts["PS_GTO_MIN_FORCE_SCALE_N"] == gto.MIN_FORCE_SCALE_N
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


@pytest.mark.parametrize("backend", ["numpy", "c"])
def test_the_smallest_force_scale_keeps_the_largest_force_finite(backend):
    """At G2 = MIN_FORCE_SCALE_N the largest accepted force gives a finite rate equal to the
    closed-form static rate (below ~5.6e-304 N it was NaN); a smaller G2 is refused, naming
    the limit, by every entry: the organs, the params and the per-muscle rule."""
    g = gto.MIN_FORCE_SCALE_N
    organs = gto.make_tendon_organs([g, 4.0], CAT, dt_s=1e-3, force_N=[MAX_FORCE_N, 1.0],
                                    backend=backend)
    ib = np.array([organs.step([MAX_FORCE_N, 1.0]) for _ in range(5)])
    assert np.all(np.isfinite(ib))
    static = static_rate_pps(CAT, MAX_FORCE_N, g)
    np.testing.assert_allclose(ib[:, 0], static, rtol=1e-12)
    for bad in (g / 2, 5e-305, 0.0):
        with pytest.raises(ValueError, match="MIN_FORCE_SCALE_N"):
            gto.make_tendon_organs([bad, 4.0], CAT, backend=backend)
    with pytest.raises(ValueError, match="MIN_FORCE_SCALE_N"):
        CAT.replace(force_scale_N=g / 2)
    with pytest.raises(ValueError, match="MIN_FORCE_SCALE_N"):
        force_scales_N(CAT, 1e-9)


def test_the_fixed_point_step_refuses_values_its_int32_formats_would_wrap():
    """1/G2 in Q24 and the forces in Q8 go to C as int32: a G2 whose 1/G2 is 2^32 + 1000 in
    Q24 wrapped silently to 1000 (the rates of G2 = 16,777 N), a force of 1e10 N to a valid
    Q8 word. Each is refused now, naming the value and the limit; at the limit it runs."""
    force = np.full(50, 10.0)
    wrapped = cgto.FX_INV_SCALE / (2**32 + 1000)
    with pytest.raises(ValueError, match="FX_MIN_FORCE_SCALE_N"):
        cgto.fixed_rates(force, 1e-3, wrapped, CAT)
    for bad in (1e10, np.nan, np.inf, 2 * MAX_FORCE_N):
        f = force.copy()
        f[7] = bad
        with pytest.raises(ValueError, match=r"MAX_FORCE_N.*\(sample 7\)"):
            cgto.fixed_rates(f, 1e-3, 4.0, CAT)
    # a slack tendon however negative: the rates of a force of 0 there
    f = force.copy()
    f[7] = -1e10
    zero = force.copy()
    zero[7] = 0.0
    np.testing.assert_array_equal(cgto.fixed_rates(f, 1e-3, 4.0, CAT),
                                  cgto.fixed_rates(zero, 1e-3, 4.0, CAT))
    # just above the limit G2 runs, and its static rate is the closed form's (Q16 rates)
    g = cgto.FX_MIN_FORCE_SCALE_N * 1.001
    ib = cgto.fixed_rates(np.full(2000, 1.0), 1e-3, g, CAT)
    assert ib[-1] == pytest.approx(float(static_rate_pps(CAT, 1.0, g)), rel=2e-3)
