"""The C spindle (spindle/native/c/spindle.c) against the numpy core and the stiff reference.

The double build follows spindle.core operation by operation, so on contractive settings
(trapezoidal rule, backward Euler) it agrees with numpy to ~1e-11 pps. Forward Euler is
chaotic where the polar velocity crosses 0 (the |v|^0.3 damping has an infinite slope there),
so it amplifies the one implementation difference between the two, numpy's SIMD ``**``
against the C library's ``pow`` (1 ulp apart); with numpy's power replaced by the same libm
``pow`` the two agree to round-off there too (1.1e-13 pps measured).
"""

from __future__ import annotations

import ctypes
import math
import subprocess

import numpy as np
import pytest

import spindle
from spindle import core
from spindle.native import abi, build
from spindle.native import spindle as native_spindle

PS_OK, PS_ERR_NULL = abi.Status.PS_OK, abi.Status.PS_ERR_NULL

try:
    build.find_compiler()
except build.CBackendError as exc:  # pragma: no cover - depends on the machine
    pytest.skip(str(exc), allow_module_level=True)

TOL_PPS = 3e-11
"""Double build vs the numpy core. Measured (2026-12-02, x86-64 gcc, numpy's SIMD power): at most
1.34e-11 pps (Ia, backward Euler at its default 0.1 ms step on Fig. 3, slow set), 8.0e-12 in the
default set (random trajectories, backward Euler), 2.2-3.7e-12 on Fig. 3 at 1 ms and on the
fast plan, 1.1e-13 for forward Euler with numpy on libm's pow; one step against core.step
1.1e-12."""
# float32 build vs the double numpy core on the protocols below: measured 0.00285 pps here
# (2026-12-02; Fig. 3 and random trajectories at 1 ms), 3.5e-4 pps for the float plan step;
# docs/c_port.md's worst figure over its settings is 0.0077 pps (trapezoidal 0.25 ms).
FLOAT_TOL_PPS = 0.01

SPEEDS = (0.11, 0.66, 1.55)
DRIVES = ((0.0, 0.0), (70.0, 0.0), (0.0, 70.0))


def fig3_protocol(dt_s: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mileusnic 2006 Fig. 3: 0.95 -> 1.08 L0 ramps from 1 s, 3.3 s; the 9 runs as columns."""
    t = np.arange(round(3.3 / dt_s) + 1) * dt_s
    runs = [(v, gd, gs) for v in SPEEDS for gd, gs in DRIVES]
    speed = np.array([r[0] for r in runs])
    end = 1.0 + (1.08 - 0.95) / speed
    length = 0.95 + speed * np.clip(t[:, None] - 1.0, 0.0, end - 1.0)
    velocity = np.where((t[:, None] > 1.0) & (t[:, None] < end), speed, 0.0)
    return length, velocity, np.array([r[1] for r in runs]), np.array([r[2] for r in runs])


def random_trajectories(seed: int, n: int = 4, duration_s: float = 2.0, dt_s: float = 2e-3):
    """Smooth random lengths in [0.6, 1.4] L0 (|dL/dt| < 4 L0/s) and stepwise random drive."""
    rng = np.random.default_rng(seed)
    t = np.arange(round(duration_s / dt_s) + 1) * dt_s
    freq = rng.uniform(0.2, 3.0, size=(5, n))
    amp = rng.uniform(0.0, 0.08, size=(5, n))
    phase = rng.uniform(0, 2 * np.pi, size=(5, n))
    arg = 2 * np.pi * freq[None] * t[:, None, None] + phase[None]
    length = 1.0 + rng.uniform(-0.1, 0.1, n) + (amp[None] * np.sin(arg)).sum(axis=1)
    velocity = (amp[None] * 2 * np.pi * freq[None] * np.cos(arg)).sum(axis=1)
    accel = -(amp[None] * (2 * np.pi * freq[None]) ** 2 * np.sin(arg)).sum(axis=1)
    hold = max(1, round(0.25 / dt_s))
    gd = np.repeat(rng.uniform(0, 150, size=(len(t) // hold + 1, n)), hold, axis=0)[:len(t)]
    gs = np.repeat(rng.uniform(0, 150, size=(len(t) // hold + 1, n)), hold, axis=0)[:len(t)]
    gd[rng.random(gd.shape) < 0.3] = 0.0
    return length, velocity, accel, gd, gs, dt_s


@pytest.fixture
def libm_pow_in_numpy(monkeypatch):
    """numpy's z = sgn(v)|v|^(a/3) with the C library's pow (what spindle.c calls)."""
    libm_pow = np.frompyfunc(math.pow, 2, 1)

    def z_from_velocity(v, c):
        return np.sign(v) * libm_pow(np.abs(v), np.broadcast_to(c.a / 3.0, v.shape)) \
            .astype(float)

    monkeypatch.setattr(core, "_z_from_velocity", z_from_velocity)


def assert_close(a, b, tol):
    assert a.ia.shape == b.ia.shape
    assert np.isfinite(b.ia).all() and np.isfinite(b.ii).all()
    d_ia = np.abs(a.ia - b.ia).max()
    d_ii = np.abs(a.ii - b.ii).max()
    assert d_ia <= tol and d_ii <= tol, (d_ia, d_ii)


@pytest.mark.parametrize(("method", "step_s"), [
    ("trapezoidal", 1e-3), ("trapezoidal", 0.25e-3), ("backward_euler", 1e-3),
])
def test_fig3_double_matches_numpy(method, step_s):
    length, velocity, gd, gs = fig3_protocol()
    kw = dict(velocity=velocity, gamma_dyn=gd, gamma_stat=gs, method=method, step=step_s)
    assert_close(spindle.simulate(length, 1e-3, **kw),
                 spindle.simulate(length, 1e-3, backend="c", **kw), TOL_PPS)


@pytest.mark.usefixtures("libm_pow_in_numpy")
@pytest.mark.parametrize("step_s", [1e-3, 0.25e-3])
def test_fig3_forward_euler_double_matches_numpy_with_the_same_pow(step_s):
    length, velocity, gd, gs = fig3_protocol()
    kw = dict(velocity=velocity, gamma_dyn=gd, gamma_stat=gs, method="forward_euler",
              step=step_s)
    assert_close(spindle.simulate(length, 1e-3, **kw),
                 spindle.simulate(length, 1e-3, backend="c", **kw), TOL_PPS)


@pytest.mark.slow
@pytest.mark.usefixtures("libm_pow_in_numpy")
@pytest.mark.parametrize("method", ["forward_euler", "backward_euler", "trapezoidal"])
def test_fig3_default_steps_double_matches_numpy(method):
    length, velocity, gd, gs = fig3_protocol()
    kw = dict(velocity=velocity, gamma_dyn=gd, gamma_stat=gs, method=method)
    assert_close(spindle.simulate(length, 1e-3, **kw),
                 spindle.simulate(length, 1e-3, backend="c", **kw), TOL_PPS)


@pytest.mark.usefixtures("libm_pow_in_numpy")
@pytest.mark.parametrize("method", ["forward_euler", "backward_euler", "trapezoidal"])
@pytest.mark.parametrize("seed", [0, 1])
def test_random_trajectories_double_matches_numpy(method, seed):
    length, velocity, accel, gd, gs, dt = random_trajectories(seed)
    step = {"forward_euler": 0.5e-3, "backward_euler": 0.5e-3, "trapezoidal": 1e-3}[method]
    for extra in ({}, {"velocity": velocity}, {"velocity": velocity, "acceleration": accel}):
        kw = dict(gamma_dyn=gd, gamma_stat=gs, method=method, step=step, **extra)
        assert_close(spindle.simulate(length, dt, **kw),
                     spindle.simulate(length, dt, backend="c", **kw), TOL_PPS)


def test_one_spindle_trace_and_human_params():
    length, _, _, gd, _, dt = random_trajectories(5, n=1)
    kw = dict(gamma_dyn=gd[:, 0], gamma_stat=30.0, params=spindle.HUMAN, step=0.5e-3)
    a = spindle.simulate(length[:, 0], dt, **kw)
    b = spindle.simulate(length[:, 0], dt, backend="c", **kw)
    assert b.ia.shape == (length.shape[0],) and b.step_s == a.step_s
    assert_close(a, b, TOL_PPS)


@pytest.mark.parametrize("method", ["backward_euler", "trapezoidal"])
def test_float_build_within_documented_tolerance(method):
    length, velocity, gd, gs = fig3_protocol()
    kw = dict(velocity=velocity, gamma_dyn=gd, gamma_stat=gs, method=method, step=1e-3)
    ref = spindle.simulate(length, 1e-3, **kw)
    f32 = native_spindle.simulate(length, 1e-3, variant="float", **kw)
    assert f32.ia.dtype == np.float64  # returned as double, computed in float
    assert_close(ref, f32, FLOAT_TOL_PPS)
    length, _, _, gd, gs, dt = random_trajectories(3)
    kw = dict(gamma_dyn=gd, gamma_stat=gs, method=method, step=1e-3)
    assert_close(spindle.simulate(length, dt, **kw),
                 native_spindle.simulate(length, dt, variant="float", **kw), FLOAT_TOL_PPS)


def test_c_backend_against_the_stiff_reference():
    pytest.importorskip("scipy")
    from spindle.reference import ramp_and_hold, solve_reference

    stim = ramp_and_hold(speed_L0_s=1.55, gamma_dyn_pps=70.0, duration_s=1.6)
    t = np.arange(0, 1.6 + 5e-4, 1e-3)
    length = np.array([stim.length_L0(x) for x in t])
    ref = solve_reference(stim, t)
    r = spindle.simulate(length, 1e-3, gamma_dyn=70.0, backend="c")
    # the numpy core's documented figure for the default setting (tests/test_spindle_reference)
    assert np.sqrt(np.mean((r.ia - ref.ia) ** 2)) <= 0.5
    assert np.sqrt(np.mean((r.ii - ref.ii) ** 2)) <= 0.5


# ---- the same ValueErrors as the numpy path ---------------------------------------------

@pytest.mark.parametrize(("kwargs", "match"), [
    (dict(length=np.full(10, 1.6)), "outside the model's range"),
    (dict(length=np.r_[1.0, np.nan]), "finite"),
    (dict(gamma_dyn=-1.0), "negative"),
    (dict(length=np.r_[1.0, 1.1]), "L0/s"),
    (dict(step=0.0), "step"),
    (dict(step=0.02), "limit"),
    (dict(dt=-1e-3), "dt="),
    (dict(gamma_stat=np.zeros(3)), "broadcast"),
    (dict(length=np.ones((2, 2, 2))), "shape"),
])
def test_bad_inputs_raise_the_numpy_errors(kwargs, match):
    base = dict(length=np.ones(10), dt=1e-3)
    base.update(kwargs)
    length, dt = base.pop("length"), base.pop("dt")
    with pytest.raises(ValueError, match=match):
        spindle.simulate(length, dt, **base)
    with pytest.raises(ValueError, match=match):
        spindle.simulate(length, dt, backend="c", **base)


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="backend='fortran'"):
        spindle.simulate(np.ones(3), 1e-3, backend="fortran")


# ---- the C API directly: status codes, state unchanged on failure -----------------------

def c_api(variant="double"):
    lib = native_spindle.library(variant)
    p = abi.params_struct(spindle.CAT, variant)
    _, PsSpindle = abi.structs(variant)
    s = PsSpindle()
    assert lib.ps_spindle_init(ctypes.byref(s), ctypes.byref(p), 1.0, 20.0, 30.0) == PS_OK
    return lib, p, s


def state_bytes(s) -> bytes:
    return ctypes.string_at(ctypes.addressof(s), ctypes.sizeof(s))


def test_init_equals_equilibrium_state():
    _, _, s = c_api()
    ref = core.equilibrium_state(1.0, 20.0, 30.0)
    np.testing.assert_allclose(np.array(s.T), ref.tension_FU[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.array(s.f), ref.activation[0], rtol=0, atol=1e-15)
    assert list(s.v) == [0.0] * 3 and list(s.z) == [0.0] * 3


def test_step_matches_core_step_and_afferents():
    lib, p, s = c_api()
    state = core.equilibrium_state(1.0, 20.0, 30.0)
    ia, ii = ctypes.c_double(), ctypes.c_double()
    for j in range(1, 200):
        L = 1.0 + 0.05 * math.sin(j / 15)
        e_ia, e_ii = core.step(state, L, 20.0 + j % 7, 30.0, 1e-3)
        assert lib.ps_spindle_step(ctypes.byref(s), ctypes.byref(p), L, 20.0 + j % 7, 30.0,
                                   1e-3, 0.5, ctypes.byref(ia), ctypes.byref(ii)) == 0
        assert abs(ia.value - e_ia[0]) <= TOL_PPS and abs(ii.value - e_ii[0]) <= TOL_PPS
    np.testing.assert_allclose(np.array(s.T), state.tension_FU[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.array(s.z), state.velocity_root[0], rtol=0, atol=1e-9)
    lib.ps_spindle_afferents(ctypes.byref(s), ctypes.byref(p), ctypes.byref(ia), None)
    assert abs(ia.value - e_ia[0]) <= TOL_PPS


@pytest.mark.parametrize("variant", ["double", "float"])
@pytest.mark.parametrize(("args", "status"), [
    ((math.nan, 0.0, 0.0, 1e-3, 0.5), "PS_ERR_NONFINITE"),
    ((1.0, math.inf, 0.0, 1e-3, 0.5), "PS_ERR_NONFINITE"),
    ((1.0, 0.0, -math.inf, 1e-3, 0.5), "PS_ERR_NONFINITE"),
    ((1.51, 0.0, 0.0, 1e-3, 0.5), "PS_ERR_LENGTH_RANGE"),
    ((0.49, 0.0, 0.0, 1e-3, 0.5), "PS_ERR_LENGTH_RANGE"),
    ((1e30, 0.0, 0.0, 1e-3, 0.5), "PS_ERR_LENGTH_RANGE"),
    ((1.0, -1e-9, 0.0, 1e-3, 0.5), "PS_ERR_NEGATIVE_DRIVE"),
    ((1.0, 0.0, -5.0, 1e-3, 0.5), "PS_ERR_NEGATIVE_DRIVE"),
    ((1.0, 0.0, 0.0, 0.0, 0.5), "PS_ERR_STEP"),
    ((1.0, 0.0, 0.0, -1e-3, 0.5), "PS_ERR_STEP"),
    ((1.0, 0.0, 0.0, math.nan, 0.5), "PS_ERR_STEP"),
    ((1.0, 0.0, 0.0, 1e-3, 1.5), "PS_ERR_METHOD"),
    ((1.0, 0.0, 0.0, 1e-3, -0.1), "PS_ERR_METHOD"),
    ((1.0, 0.0, 0.0, 1e-3, math.nan), "PS_ERR_METHOD"),
    ((1.2, 0.0, 0.0, 1e-3, 0.5), "PS_ERR_SPEED"),
])
def test_bad_step_inputs_give_their_status_and_leave_the_state(variant, args, status):
    lib, p, s = c_api(variant)
    before = state_bytes(s)
    ia = abi.real_type(variant)(-7.0)
    code = lib.ps_spindle_step(ctypes.byref(s), ctypes.byref(p), *args, ctypes.byref(ia), None)
    assert abi.status_name(code) == status
    assert state_bytes(s) == before
    assert ia.value == -7.0


def test_null_pointers_and_bad_params():
    lib, p, s = c_api()
    step = lib.ps_spindle_step
    assert step(None, ctypes.byref(p), 1.0, 0, 0, 1e-3, 0.5, None, None) == PS_ERR_NULL
    assert step(ctypes.byref(s), None, 1.0, 0, 0, 1e-3, 0.5, None, None) == PS_ERR_NULL
    assert lib.ps_spindle_init(None, ctypes.byref(p), 1.0, 0, 0) == PS_ERR_NULL
    assert lib.ps_params_check(None) == PS_ERR_NULL
    assert lib.ps_params_check(ctypes.byref(p)) == PS_OK
    lib.ps_spindle_afferents(None, None, None, None)  # documented no-op
    bad = abi.params_struct(spindle.CAT)
    bad.a[1] = 1.0
    assert abi.status_name(lib.ps_params_check(ctypes.byref(bad))) == "PS_ERR_CONFIG"
    bad = abi.params_struct(spindle.CAT)
    bad.KSR[0] = math.nan
    assert abi.status_name(lib.ps_params_check(ctypes.byref(bad))) == "PS_ERR_CONFIG"


# ---- the embedded fast path (ps_plan) ---------------------------------------------------

@pytest.mark.parametrize("variant", ["double", "float"])
@pytest.mark.parametrize(("theta", "step_s"), [(0.5, 1e-3), (1.0, 1e-3), (0.5, 5e-3)])
def test_plan_step_matches_the_exact_step(variant, theta, step_s):
    """ps_spindle_step_plan (precomputed constants, bounded Newton start) = ps_spindle_step
    to round-off: 3.7e-12 pps measured in double; float32 3.5e-4 pps, within the float
    tolerance."""
    lib = native_spindle.library(variant)
    real = abi.real_type(variant)
    p = abi.params_struct(spindle.CAT, variant)
    _, PsSpindle = abi.structs(variant)
    plan = abi.plan_struct(variant)()
    assert lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(p), step_s, theta) == PS_OK
    length = fig3_protocol(step_s)[0][:, 7]  # 1.55 L0/s
    a, b = PsSpindle(), PsSpindle()
    for s in (a, b):
        assert lib.ps_spindle_init(ctypes.byref(s), ctypes.byref(p), length[0], 70.0, 20.0) == PS_OK
    ia_a, ii_a, ia_b, ii_b = real(), real(), real(), real()
    worst = 0.0
    for j in range(1, len(length)):
        drive = 70.0 if j < len(length) // 2 else 35.0  # a drive change exercises a0 != a1
        assert lib.ps_spindle_step(ctypes.byref(a), ctypes.byref(p), length[j], drive, 20.0,
                                   step_s, theta, ctypes.byref(ia_a), ctypes.byref(ii_a)) == 0
        assert lib.ps_spindle_step_plan(ctypes.byref(b), ctypes.byref(plan), length[j], drive,
                                        20.0, ctypes.byref(ia_b), ctypes.byref(ii_b)) == 0
        worst = max(worst, abs(ia_a.value - ia_b.value), abs(ii_a.value - ii_b.value))
    assert worst <= (TOL_PPS if variant == "double" else FLOAT_TOL_PPS)


def test_plan_refuses_bad_setup_and_inputs():
    lib, p, s = c_api()
    PsPlan = abi.plan_struct()
    plan = PsPlan()
    names = abi.status_name
    assert names(lib.ps_plan_init(None, ctypes.byref(p), 1e-3, 0.5)) == "PS_ERR_NULL"
    assert names(lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(p), 0.0, 0.5)) == "PS_ERR_STEP"
    assert names(lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(p), 1e-3, 2.0)) \
        == "PS_ERR_METHOD"
    bad = abi.params_struct(spindle.CAT)
    bad.M[2] = -1.0
    assert names(lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(bad), 1e-3, 0.5)) \
        == "PS_ERR_CONFIG"
    assert bytes(plan) == bytes(PsPlan())  # untouched on failure
    assert lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(p), 1e-3, 0.5) == PS_OK
    before = state_bytes(s)
    for args, status in (((math.nan, 0.0, 0.0), "PS_ERR_NONFINITE"),
                         ((1.6, 0.0, 0.0), "PS_ERR_LENGTH_RANGE"),
                         ((1.0, -1.0, 0.0), "PS_ERR_NEGATIVE_DRIVE"),
                         ((1.02, 0.0, 0.0), "PS_ERR_SPEED")):
        code = lib.ps_spindle_step_plan(ctypes.byref(s), ctypes.byref(plan), *args, None, None)
        assert names(code) == status
        assert state_bytes(s) == before


# ---- batches of independent spindles (ps_spindle_batch_step, CSpindleBatch) ---------------

def batch_inputs(seed: int = 5, n: int = 48, duration_s: float = 1.5):
    """Smooth random lengths of n spindles at 1 ms steps, each with its own stepwise random
    drive (drive changes exercise the activation filter's a0 != a1 path)."""
    length, _, _, gd, gs, _ = random_trajectories(seed, n=n, duration_s=duration_s, dt_s=1e-3)
    return length, gd, gs


@pytest.mark.parametrize("theta", [0.5, 1.0])
def test_batch_step_matches_the_numpy_core(theta):
    """n spindles in one ps_spindle_batch_step call per step = spindle.core.step on the same
    inputs (HUMAN constants), to 1e-9 pps over 1.5 s of 1 ms steps."""
    length, gd, gs = batch_inputs()
    ref = core.equilibrium_state(length[0], gd[0], gs[0], spindle.HUMAN)
    batch = native_spindle.CSpindleBatch(ref.copy(), spindle.HUMAN, 1e-3, theta)
    for got, want in zip(batch.afferents(), core.afferents(ref, spindle.HUMAN), strict=True):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    method = "trapezoidal" if theta == 0.5 else "backward_euler"
    worst, top = 0.0, 0.0
    for j in range(1, length.shape[0]):
        ia, ii = batch.step(length[j], gd[j], gs[j])
        ref_ia, ref_ii = core.step(ref, length[j], gd[j], gs[j], 1e-3, spindle.HUMAN, method)
        worst = max(worst, np.abs(ia - ref_ia).max(), np.abs(ii - ref_ii).max())
        top = max(top, ref_ia.max())
    assert top > 50  # the comparison covers real firing
    assert worst <= 1e-9
    state = batch.state()
    np.testing.assert_allclose(state.tension_FU, ref.tension_FU, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(state.length_L0, ref.length_L0)


def test_batch_step_names_the_first_failing_spindle_anywhere():
    """Whichever spindles fail (first, middle, last, two at once), the first one is named and
    every spindle is left as it was; then each spindle's step is bit for bit its step in a
    batch of one."""
    n = 11
    length, gd, gs = batch_inputs(n=n, duration_s=0.01)
    state = core.equilibrium_state(length[0], gd[0], gs[0], spindle.HUMAN)
    batch = native_spindle.CSpindleBatch(state, spindle.HUMAN)
    batch.step(length[1], gd[1], gs[1])
    before = batch.fields.copy()
    for bad in ([0], [3], [5], [6], [10], [7, 2], [9, 8]):
        L = length[2].copy()
        L[bad] = 1.6
        with pytest.raises(ValueError, match=f"spindle {min(bad)} of {n} failed with "
                                             "PS_ERR_LENGTH_RANGE"):
            batch.step(L, gd[2], gs[2])
        np.testing.assert_array_equal(batch.fields, before)
    ia, ii = (x.copy() for x in batch.step(length[2], gd[2], gs[2]))
    one = native_spindle.CSpindleBatch(
        core.equilibrium_state(length[0][:1], gd[0][:1], gs[0][:1], spindle.HUMAN),
        spindle.HUMAN)
    for j in range(n):  # each spindle alone: the same bits
        one.fields[...] = before[j:j + 1]
        got = one.step(length[2][j:j + 1], gd[2][j:j + 1], gs[2][j:j + 1])
        assert (got[0][0], got[1][0]) == (ia[j], ii[j])


def test_batch_steps_equal_one_call_per_step_and_are_atomic_over_all_steps():
    """ps_spindle_batch_steps: k steps in one call = k ps_spindle_batch_step calls, bit for
    bit (rates of the last); a failure at any step leaves every spindle as before the call
    and names the step and the spindle."""
    n, k = 21, 6  # not a multiple of the lanes
    length, gd, gs = batch_inputs(n=n, duration_s=0.05)
    state = core.equilibrium_state(length[0], gd[0], gs[0], spindle.HUMAN)
    one, many = (native_spindle.CSpindleBatch(state.copy(), spindle.HUMAN) for _ in range(2))
    for start in (1, 1 + k, 1 + 2 * k):
        rows = slice(start, start + k)
        for j in range(start, start + k):
            want = [x.copy() for x in one.step(length[j], gd[j], gs[j])]
        got = many.steps(length[rows], gd[rows], gs[rows])
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_array_equal(many.fields, one.fields)
    before = many.fields.copy()
    rows = slice(1 + 3 * k, 1 + 4 * k)
    for step, spindle_j, bad, error in ((0, 4, 1.6, ValueError), (3, 17, 1.6, ValueError),
                                        (5, 0, math.nan, ValueError)):
        L = length[rows].copy()
        L[step, spindle_j] = bad
        with pytest.raises(error, match=f"spindle {spindle_j} of {n} failed at step {step} "
                                        f"of {k} with"):
            many.steps(L, gd[rows], gs[rows])
        np.testing.assert_array_equal(many.fields, before)
    with pytest.raises(ValueError, match=r"each must be \(steps, 21\)"):
        many.steps(length[rows][:, :5], gd[rows], gs[rows])
    failed_step, failed = ctypes.c_long(9), ctypes.c_long(9)
    assert many.lib.ps_spindle_batch_steps(
        many._address, n, -1, ctypes.byref(many._plan), None, None, None, None, None, None,
        None, ctypes.byref(failed_step), ctypes.byref(failed)) == abi.Status.PS_ERR_ARGUMENT
    assert (failed_step.value, failed.value) == (-1, -1)
    assert many.lib.ps_spindle_batch_steps(
        many._address, n, 2, ctypes.byref(many._plan), None, None, None, None, None, None,
        None, None, None) == PS_ERR_NULL


def test_batch_step_is_atomic_and_names_the_failing_spindle():
    length, gd, gs = batch_inputs(n=6, duration_s=0.01)
    state = core.equilibrium_state(length[0], gd[0], gs[0], spindle.HUMAN)
    batch = native_spindle.CSpindleBatch(state, spindle.HUMAN)
    batch.step(length[1], gd[1], gs[1])
    before = batch.fields.copy()
    for bad, error, status in ((1.6, ValueError, "PS_ERR_LENGTH_RANGE"),
                               (math.nan, ValueError, "PS_ERR_NONFINITE"),
                               (length[1][4] + 0.02, ValueError, "PS_ERR_SPEED")):
        L = length[2].copy()
        L[4] = bad  # spindles 0-3 step first, then 4 fails: they must be put back
        with pytest.raises(error, match=f"spindle 4 of 6 failed with {status}"):
            batch.step(L, gd[2], gs[2])
        np.testing.assert_array_equal(batch.fields, before)
    with pytest.raises(ValueError, match=r"each must be \(6,\)"):
        batch.step(length[2][:5], gd[2], gs[2])
    # the C entry points' argument checks
    lib = batch.lib
    failed = ctypes.c_long(7)
    args = (batch.lib, batch._address, ctypes.byref(batch._plan))
    assert lib.ps_spindle_batch_step(args[1], -1, args[2], None, None, None, None, None, None,
                                     ctypes.byref(failed)) == abi.Status.PS_ERR_ARGUMENT
    assert failed.value == -1
    assert lib.ps_spindle_batch_step(args[1], 6, args[2], None, None, None, None, None, None,
                                     None) == PS_ERR_NULL
    assert lib.ps_spindle_batch_step(None, 0, None, None, None, None, None, None, None,
                                     None) == PS_OK
    assert lib.ps_spindle_batch_afferents(args[1], 6, args[2], None, None) == PS_ERR_NULL
    np.testing.assert_array_equal(batch.fields, before)
    batch.step(length[2], gd[2], gs[2])  # still usable


# ---- the batch's SIMD lanes against the scalar step ------------------------------------

def scalar_steps(batch, before, L, gd, gs):
    """Each spindle of ``before`` (an (n, 15) state array) stepped alone by
    ps_spindle_step_plan: (new states, Ia, II, statuses)."""
    lib, variant = batch.lib, batch.variant
    real = abi.real_type(variant)
    _, PsSpindle = abi.structs(variant)
    n = before.shape[0]
    out = before.copy()
    ia, ii = np.zeros(n, batch.dtype), np.zeros(n, batch.dtype)
    codes = np.zeros(n, int)
    r_ia, r_ii = real(), real()
    for j in range(n):
        s = PsSpindle.from_buffer_copy(before[j].tobytes())
        codes[j] = lib.ps_spindle_step_plan(ctypes.byref(s), ctypes.byref(batch._plan),
                                            L[j], gd[j], gs[j], ctypes.byref(r_ia),
                                            ctypes.byref(r_ii))
        out[j] = np.frombuffer(bytes(s), dtype=batch.dtype)
        ia[j], ii[j] = r_ia.value, r_ii.value
    return out, ia, ii, codes


def random_walk(rng, n: int, steps: int, step_s: float):
    """Lengths of n spindles moving at random speeds up to ~9 L0/s with reversals (within
    the speed limit of 10 L0/s), and drives that jump at random (sometimes to 0, sometimes
    unchanged for a while)."""
    speed = rng.uniform(-9.0, 9.0, (steps, n)) * (rng.random((steps, n)) < 0.7)
    speed[rng.random((steps, n)) < 0.1] *= -1.0  # reversals
    L = np.clip(rng.uniform(0.7, 1.3, n) + np.cumsum(speed * step_s, axis=0), 0.55, 1.45)
    L = np.vstack([L[:1], L])
    dL = np.clip(np.diff(L, axis=0), -9.9 * step_s, 9.9 * step_s)  # the clip must not speed up
    L = L[0] + np.vstack([np.zeros(n), np.cumsum(dL, axis=0)])
    drives = []
    for _ in range(2):
        d = rng.uniform(0.0, 200.0, (steps + 1, n))
        hold = rng.random((steps + 1, n)) < 0.6
        for j in range(1, steps + 1):
            d[j, hold[j]] = d[j - 1, hold[j]]
        d[rng.random(d.shape) < 0.1] = 0.0
        drives.append(d)
    return L, drives[0], drives[1]


@pytest.mark.parametrize("variant", ["double", "float"])
@pytest.mark.parametrize(("theta", "step_s", "params", "n"), [
    (0.5, 1e-3, "HUMAN", 37), (1.0, 1e-3, "CAT", 13), (0.5, 5e-3, "CAT", 26)])
def test_batch_lanes_equal_the_scalar_step_bit_for_bit(variant, theta, step_s, params, n):
    """ps_spindle_batch_step (SIMD lanes for the a = 0.3 implicit plan, the tail n % lanes
    scalar) gives every spindle exactly the state and rates of its own ps_spindle_step_plan,
    over random lengthening, shortening, reversals and drive jumps from random states."""
    rng = np.random.default_rng(n)
    p = getattr(spindle, params)
    steps = 60
    L, gd, gs = random_walk(rng, n, steps, step_s)
    state = core.equilibrium_state(L[0], gd[0], gs[0], p)
    state.polar_velocity_L0_s[...] = rng.uniform(-2.0, 2.0, (n, 3))  # start off rest too
    state.velocity_root[...] = np.sign(state.polar_velocity_L0_s) \
        * np.abs(state.polar_velocity_L0_s) ** 0.1
    batch = native_spindle.CSpindleBatch(state, p, step_s, theta, variant)
    moved = 0.0
    for j in range(1, steps + 1):
        before = batch.fields.copy()
        want, want_ia, want_ii, codes = scalar_steps(batch, before, L[j], gd[j], gs[j])
        assert (codes == PS_OK).all()
        ia, ii = batch.step(L[j], gd[j], gs[j])
        np.testing.assert_array_equal(batch.fields, want)
        np.testing.assert_array_equal(ia, want_ia)
        np.testing.assert_array_equal(ii, want_ii)
        moved = max(moved, np.abs(before[:, 3:6]).max())
    assert moved > 1.0  # the polar regions did move (not a batch at rest)


@pytest.mark.parametrize("variant", ["double", "float"])
@pytest.mark.parametrize("n", [8, 11])
def test_batch_lanes_failure_in_a_block_or_the_tail_is_atomic(variant, n):
    """A spindle that fails in the middle of a block, at a block's edge or in the tail (n % 8)
    gives the status and index of the scalar loop, and leaves every spindle as it was; a
    failure found only after the solve (an infinite tension: no convergence) too."""
    rng = np.random.default_rng(3)
    L, gd, gs = random_walk(rng, n, 2, 1e-3)
    state = core.equilibrium_state(L[0], gd[0], gs[0], spindle.HUMAN)
    batch = native_spindle.CSpindleBatch(state, spindle.HUMAN, 1e-3, 0.5, variant)
    batch.step(L[1], gd[1], gs[1])
    before = batch.fields.copy()
    lib = batch.lib
    failed = ctypes.c_long()
    for bad in ([1], [3], [4], [n - 1], [n - 2, 2], [5, n - 1]):
        for field, value, status in ((0, 1.6, "PS_ERR_LENGTH_RANGE"),
                                     (1, -1.0, "PS_ERR_NEGATIVE_DRIVE"),
                                     (0, L[1] + 0.02, "PS_ERR_SPEED"),
                                     ("state", np.inf, None)):
            x = [L[2].copy(), gd[2].copy(), gs[2].copy()]
            if field == "state":  # a tension that makes the step non-finite
                batch.fields[bad, 0] = value
            else:
                x[field][bad] = value if np.isscalar(value) else value[bad]
            start = batch.fields.copy()
            arrays = [np.ascontiguousarray(a, dtype=batch.dtype) for a in x]
            code = lib.ps_spindle_batch_step(
                batch._address, n, ctypes.byref(batch._plan), arrays[0].ctypes.data,
                arrays[1].ctypes.data, arrays[2].ctypes.data, batch._backup_address,
                batch.ia_pps.ctypes.data, batch.ii_pps.ctypes.data, ctypes.byref(failed))
            _, _, _, codes = scalar_steps(batch, start, *arrays)
            assert (codes[:min(bad)] == PS_OK).all() and codes[min(bad)] != PS_OK
            assert code == codes[min(bad)]
            assert status is None or abi.status_name(code) == status
            assert failed.value == min(bad)
            np.testing.assert_array_equal(batch.fields, start)
            batch.fields[...] = before
    want, want_ia, _, _ = scalar_steps(batch, before, L[2], gd[2], gs[2])
    ia, _ = batch.step(L[2], gd[2], gs[2])  # still usable
    np.testing.assert_array_equal(batch.fields, want)
    np.testing.assert_array_equal(ia, want_ia)


@pytest.mark.parametrize("defines", [("-DPS_NEWTON_ITER=3",), ("-UPS_FAST_CBRT",),
                                     ("-DPS_LANES_NO_AVX2",)])
def test_batch_lanes_equal_the_scalar_step_in_other_builds(tmp_path, defines):
    """The lanes follow the compile-time options of the scalar step (a fixed Newton
    iteration count; libm's cube root for the start) and are bit for bit the scalar step in
    the baseline instruction set too (-DPS_LANES_NO_AVX2: lanes without the AVX2 copy)."""
    out = tmp_path / "libvariant.so"
    flags = [*build.compile_flags("double"), *defines]
    if "-UPS_FAST_CBRT" in defines:
        flags = [f for f in flags if not f.startswith(("-DPS_FAST_CBRT", "-DPS_CBRT_REFINE"))]
    cmd = [*build.compiler_command(), *flags, "-I", str(build.SOURCE_DIR),
           *map(str, build.sources()), "-o", str(out), "-lm"]
    subprocess.run(cmd, check=True, capture_output=True)
    lib = ctypes.CDLL(str(out))
    _, PsSpindle = abi.structs()
    plan = abi.plan_struct()()
    p = abi.params_struct(spindle.HUMAN)
    assert lib.ps_plan_init(ctypes.byref(plan), ctypes.byref(p), ctypes.c_double(1e-3),
                            ctypes.c_double(0.5)) == PS_OK
    n, steps = 19, 40
    rng = np.random.default_rng(11)
    L, gd, gs = random_walk(rng, n, steps, 1e-3)
    state = core.equilibrium_state(L[0], gd[0], gs[0], spindle.HUMAN)
    spindles, backup = (PsSpindle * n)(), (PsSpindle * n)()
    fields = np.frombuffer(spindles, dtype=np.float64).reshape(n, 15)
    for name, a, b in native_spindle.STATE_FIELDS:
        value = getattr(state, name)
        fields[:, a:b] = value if value.ndim == 2 else value[:, None]
    ia, ii = np.zeros(n), np.zeros(n)
    r_ia, r_ii, failed = ctypes.c_double(), ctypes.c_double(), ctypes.c_long()
    for j in range(1, steps + 1):
        x = [np.ascontiguousarray(a[j]) for a in (L, gd, gs)]
        want = fields.copy()
        want_ia, want_ii = np.zeros(n), np.zeros(n)
        for k in range(n):
            s = PsSpindle.from_buffer(want[k])
            assert lib.ps_spindle_step_plan(
                ctypes.byref(s), ctypes.byref(plan), ctypes.c_double(x[0][k]),
                ctypes.c_double(x[1][k]), ctypes.c_double(x[2][k]), ctypes.byref(r_ia),
                ctypes.byref(r_ii)) == PS_OK
            want_ia[k], want_ii[k] = r_ia.value, r_ii.value
        assert lib.ps_spindle_batch_step(
            ctypes.c_void_p(ctypes.addressof(spindles)), ctypes.c_long(n), ctypes.byref(plan),
            ctypes.c_void_p(x[0].ctypes.data), ctypes.c_void_p(x[1].ctypes.data),
            ctypes.c_void_p(x[2].ctypes.data), ctypes.c_void_p(ctypes.addressof(backup)),
            ctypes.c_void_p(ia.ctypes.data), ctypes.c_void_p(ii.ctypes.data),
            ctypes.byref(failed)) == PS_OK
        np.testing.assert_array_equal(fields, want)
        np.testing.assert_array_equal(ia, want_ia)
        np.testing.assert_array_equal(ii, want_ii)
