"""Faults at the edges of the valid inputs in the spindle core and the batch simulator, numpy and C.

- the range ends (0.5 and 1.5 L0) at rest and in motion over the corners of the drive grid:
  the damping's polar-length factor is clipped at 0, so a polar region shorter than R (0.5 L0
  with static drive) is undamped instead of driven, and the step equation stays monotone;
- the work per call is bounded: more than MAX_SUBSTEPS internal steps per sample interval is
  refused before anything is allocated;
- sub-step lengths between valid samples stay in range and under the speed limit, the same
  lengths in both backends, and are counted;
- drives too large for g^2 saturate the activation at 1 in both backends;
- long inputs are streamed in chunks with results identical to one chunk, and a peak memory
  of about input + output + 70 MB.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import spindle
from spindle.native import build
from spindle.simulation import MAX_SUBSTEPS
from spindle.substeps import substep_lengths

try:
    build.find_compiler()
    BACKENDS = ["numpy", "c"]
except build.CBackendError:  # pragma: no cover - depends on the machine
    BACKENDS = ["numpy"]

needs_c = pytest.mark.skipif("c" not in BACKENDS, reason="no C compiler")

DRIVE_CORNERS = [(gd, gs) for gd in (0.0, 150.0, 300.0) for gs in (0.0, 150.0, 300.0)]
METHOD_STEP = [("trapezoidal", 1e-3), ("backward_euler", 1e-3), ("forward_euler", None),
               ("forward_euler", 2.5e-4)]  # the largest step the README names for the ends


def assert_backends_agree(a, b):
    """numpy and C solve the same equations to |dz| <= 1e-9: 1e-12 pps, or 2e-14 of the rate
    where the CAT gains drive it past 50 pps (1e-11 pps at 1300 pps at the range ends, as
    before the range-end fixes)."""
    for x, y in ((a.ia, b.ia), (a.ii, b.ii)):
        assert np.abs(x - y).max() <= 1e-12 + 2e-14 * np.abs(x).max()


def range_end_trace(end: float, dt: float = 1e-3) -> np.ndarray:
    """At rest at the range end (30 ms), a ramp away to 1.0 L0 at 8 L0/s, a hold, the ramp
    back into the end and a 150 ms hold there."""
    ramp = np.linspace(end, 1.0, round(abs(1.0 - end) / (8.0 * dt)) + 1)
    return np.concatenate([np.full(30, end), ramp, np.full(20, 1.0), ramp[::-1],
                           np.full(150, end)])


def assert_physiological(r, limit_pps=2500.0):
    for rate in (r.ia, r.ii):
        assert np.isfinite(rate).all()
        assert rate.min() >= 0.0
        assert rate.max() < limit_pps


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("end", [0.5, 1.5])
@pytest.mark.parametrize("gamma_stat", [0.0, 100.0, 150.0, 300.0])
def test_a_spindle_at_rest_at_a_range_end_stays_at_its_equilibrium(backend, end, gamma_stat):
    """Issue 13 item 2: at rest at 0.5 L0 with gs >= 100 the first step failed ("did not
    converge ... nan") in both backends. At rest the implicit methods' rates are the
    closed-form equilibrium's. (Forward Euler chatters about v = 0 at rest, by up to 130 pps
    at 1 ms and 1.5 L0, a property of the explicit method: see the next test.)"""
    expected = spindle.afferents(spindle.equilibrium_state(end, 150.0, gamma_stat))
    for method, step in METHOD_STEP[:2]:  # implicit
        r = spindle.simulate(np.full(20, end), 1e-3, gamma_dyn=150.0, gamma_stat=gamma_stat,
                             method=method, step=step, backend=backend)
        np.testing.assert_allclose(r.ia, expected[0][0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(r.ii, expected[1][0], rtol=0, atol=1e-9)


@pytest.mark.parametrize("end", [0.5, 1.5])
@pytest.mark.parametrize(("method", "step"), METHOD_STEP)
def test_rest_and_ramps_at_the_range_ends_over_the_drive_grid(end, method, step):
    """Every corner of the drive grid, rest and ramps out of and into each range end:
    finite, non-negative, bounded; the vectorised (n = 9) and one-spindle paths agree, and the
    C backend agrees with numpy (implicit methods). Forward Euler at its default step (at its
    1.2 ms limit it blows up on these 8 L0/s ramps, as it always did)."""
    L = range_end_trace(end)
    gd = np.array([c[0] for c in DRIVE_CORNERS])
    gs = np.array([c[1] for c in DRIVE_CORNERS])
    lengths = np.repeat(L[:, None], len(DRIVE_CORNERS), axis=1)
    together = spindle.simulate(lengths, 1e-3, gamma_dyn=gd, gamma_stat=gs, method=method,
                                step=step)
    assert_physiological(together)
    if method == "forward_euler":
        return  # the explicit path is the vectorised one at any n
    for j, (gdj, gsj) in enumerate(DRIVE_CORNERS):
        alone = spindle.simulate(L, 1e-3, gamma_dyn=gdj, gamma_stat=gsj, method=method,
                                 step=step)
        np.testing.assert_allclose(alone.ia, together.ia[:, j], rtol=0, atol=1e-9)
        if "c" in BACKENDS and method != "forward_euler":
            assert_backends_agree(alone, spindle.simulate(
                L, 1e-3, gamma_dyn=gdj, gamma_stat=gsj, method=method, step=step,
                backend="c"))


@needs_c
@pytest.mark.parametrize("end", [0.5, 1.5])
def test_c_forward_euler_at_the_range_ends_is_finite(end):
    """Forward Euler in C (chaotic where v crosses 0, so no tight agreement): finite and
    non-negative over the drive grid (two corners here: 50 sub-steps per sample)."""
    L = range_end_trace(end)
    for gd, gs in (DRIVE_CORNERS[0], DRIVE_CORNERS[-1]):
        assert_physiological(spindle.simulate(L, 1e-3, gamma_dyn=gd, gamma_stat=gs,
                                              method="forward_euler", backend="c"))


@pytest.mark.parametrize(("end", "gamma_dyn", "gamma_stat"), [
    (1.5, 0.0, 0.0), (1.5, 300.0, 300.0), (1.5, 0.0, 150.0), (0.5, 0.0, 0.0),
])
def test_ramps_into_the_range_ends_match_the_stiff_reference(end, gamma_dyn, gamma_stat):
    """Where the polar region stays longer than R the clip never acts and the model is the
    published one: the trapezoidal rule at 0.25 ms within 1 pps of scipy's Radau. (Where it
    gets shorter, e.g. a 2 L0/s ramp into 0.5 L0 with 300 pps dynamic drive, the published
    equation has a negative damping there and the two models differ by design.)"""
    pytest.importorskip("scipy")
    from spindle.reference import Stimulus, solve_reference

    speed, start, t_on, duration = 2.0, 1.0, 0.0, 0.6
    sign = 1.0 if end > start else -1.0
    t_off = t_on + abs(end - start) / speed

    def length(t):
        return start + sign * speed * min(max(t - t_on, 0.0), t_off - t_on)

    def velocity(t):
        return sign * speed if t_on <= t < t_off else 0.0

    stimulus = Stimulus(length, velocity, lambda t: 0.0, duration, (t_off,), gamma_dyn,
                        gamma_stat)
    t = np.arange(0.0, duration, 1e-3)
    ref = solve_reference(stimulus, t)
    L = np.array([length(x) for x in t])
    V = np.array([velocity(x) for x in t])
    for backend in BACKENDS:
        r = spindle.simulate(L, 1e-3, velocity=V, gamma_dyn=gamma_dyn, gamma_stat=gamma_stat,
                             step=0.25e-3, backend=backend)
        late = t > t_off + 0.05  # away from the ramp's corner
        assert np.abs(r.ia - ref.ia)[late].max() < 1.0
        assert np.abs(r.ii - ref.ii)[late].max() < 1.0


# -- bounded work -------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dt", [1e5, 1e9, 1e300])
@pytest.mark.parametrize("samples", [1, 3])
def test_a_huge_sample_interval_is_refused_at_once(backend, dt, samples, monkeypatch):
    """Issue 13 item 3: simulate(np.ones(1), 1e5) ran > 40 s, 1e9 ran out of memory (numpy)
    or forever (C). More than MAX_SUBSTEPS internal steps per interval is refused, naming the
    value and the limit, before any work: no spindle set up or stepped (numpy: neither
    core.equilibrium_state nor core.advance called; C: no library entry point called) and no
    more than 1 MB allocated."""
    from spindle import core
    from spindle.native import spindle as native_spindle

    spindle.simulate(np.ones(2), 1e-3, backend=backend)  # the C library loaded beforehand
    calls = []
    for name in ("equilibrium_state", "advance"):
        monkeypatch.setattr(core, name, lambda *a, name=name, **k: calls.append(name))
    lib = native_spindle.library("double")
    for name in [n for n in dir(lib) if n.startswith("ps_")]:
        monkeypatch.setattr(lib, name, lambda *a, name=name: calls.append(name))
    tracemalloc.start()
    try:
        with pytest.raises(ValueError, match=re.escape(f"dt={dt!r} s needs ") + ".* above the "
                                             f"limit MAX_SUBSTEPS = {MAX_SUBSTEPS}"):
            spindle.simulate(np.ones(samples), dt, backend=backend)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert calls == []
    assert peak < 1e6  # measured ~20 kB (the message and the checks' small arrays)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_sample_interval_within_the_limit_runs(backend):
    r = spindle.simulate(np.array([1.0, 1.0, 1.02]), 0.5, backend=backend)  # 500 sub-steps
    assert np.isfinite(r.ia).all() and r.step_s == pytest.approx(1e-3)


# -- sub-steps between samples ------------------------------------------------------------


EDGE_TRACES = [
    np.array([1.46, 1.48, 1.5, 1.5, 1.48, 1.46]),  # the issue's: Hermite reaches 1.5024 L0
    np.array([0.54, 0.52, 0.5, 0.5, 0.52, 0.54]),
    np.array([1.0, 1.0, 1.049, 1.098, 1.098, 1.098]),  # 9.8 L0/s between still samples
    np.array([1.0, 0.951, 0.951, 1.0, 1.049, 1.049]),
]


@pytest.mark.parametrize("L", EDGE_TRACES)
def test_sub_step_lengths_stay_in_range_and_under_the_speed_limit(L):
    dt, k = 5e-3, 5
    Lc = L[:, None]
    raw, _ = substep_lengths(Lc, [], k, dt)  # linear: never outside
    velocity = np.gradient(Lc, dt, axis=0)
    steps, limited = substep_lengths(Lc, [velocity], k, dt)
    path = np.concatenate([Lc[:1], steps])[:, 0]
    h = dt / k
    assert path.min() >= 0.5 and path.max() <= 1.5
    assert np.abs(np.diff(path)).max() / h <= spindle.MAX_SPEED_L0_S
    assert np.array_equal(path[::k], L)  # every interval ends on its sample
    # the raw cubic Hermite curve leaves the limits on these traces; the count says how often
    hermite = (np.array([[2 * s**3 - 3 * s**2 + 1, -2 * s**3 + 3 * s**2, s**3 - 2 * s**2 + s,
                          s**3 - s**2] for s in np.arange(1, k) / k]))
    curve = (hermite[:, 0] * L[:-1, None] + hermite[:, 1] * L[1:, None]
             + dt * (hermite[:, 2] * velocity[:-1] + hermite[:, 3] * velocity[1:]))
    full = np.concatenate([L[:1], np.column_stack([curve, L[1:]]).ravel()])
    outside = (full.min() < 0.5 or full.max() > 1.5
               or np.abs(np.diff(full)).max() / h > spindle.MAX_SPEED_L0_S)
    assert outside and limited > 0
    assert raw.shape == steps.shape


@pytest.mark.parametrize("L", EDGE_TRACES)
@pytest.mark.parametrize("method", ["trapezoidal", "backward_euler"])
def test_backends_agree_where_sub_steps_overshoot_the_range_or_the_speed_limit(L, method):
    """Issue 13 item 4: numpy integrated the overshooting sub-steps, C raised mid-run."""
    results = [spindle.simulate(L, 5e-3, method=method, gamma_stat=150.0, backend=b)
               for b in BACKENDS]
    for r in results:
        assert_physiological(r)
        assert r.substeps_limited > 0
    if len(results) == 2:
        assert results[0].substeps_limited == results[1].substeps_limited
        assert_backends_agree(*results)


# -- huge drives --------------------------------------------------------------------------


@pytest.mark.parametrize("drive", [1e150, 1e155, 1e200, 1e300, np.finfo(float).max])
def test_huge_drives_saturate_the_activation(drive):
    """Issue 13 item 8: numpy's drive^2 overflowed to inf/inf = NaN from 1.3e154 pps on
    (C saturated). Both give activation 1 and finite tension, and agree."""
    state = spindle.equilibrium_state(1.0, drive, drive)
    assert np.isfinite(state.tension_FU).all()
    np.testing.assert_array_equal(state.activation, 1.0)
    L = np.linspace(1.0, 1.05, 40)
    runs = {b: spindle.simulate(L, 1e-3, gamma_dyn=drive, gamma_stat=drive, backend=b)
            for b in BACKENDS}
    for r in runs.values():
        assert np.isfinite(r.ia).all() and np.isfinite(r.ii).all()
    saturated = spindle.simulate(L, 1e-3, gamma_dyn=1e9, gamma_stat=1e9)
    np.testing.assert_allclose(runs["numpy"].ia, saturated.ia, rtol=0, atol=1e-9)
    if "c" in runs:
        assert_backends_agree(runs["numpy"], runs["c"])
    # many spindles: the vectorised step
    many = spindle.simulate(np.repeat(L[:, None], 12, axis=1), 1e-3, gamma_dyn=drive,
                            gamma_stat=drive)
    np.testing.assert_allclose(many.ia[:, 5], runs["numpy"].ia, rtol=0, atol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_an_infinite_drive_is_refused(backend):
    with pytest.raises(ValueError, match="gamma_stat_pps contains inf; every value must be"):
        spindle.equilibrium_state(1.0, 0.0, np.inf)
    with pytest.raises(ValueError, match="gamma_dyn_pps contains inf"):
        spindle.simulate(np.ones(5), 1e-3, gamma_dyn=np.inf, backend=backend)


# -- streaming ----------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("n", [1, 3])
@pytest.mark.parametrize("dt", [1e-3, 2.5e-3])
def test_chunked_results_equal_one_chunk_bit_for_bit(backend, n, dt):
    """Issue 13 item 9: long inputs are streamed in chunks; the chunk size changes memory
    only."""
    rng = np.random.default_rng(n)
    t = np.arange(0, 0.3, dt)
    L = 1.0 + 0.499 * np.sin(2 * np.pi * (2.0 + rng.random(n)) * t[:, None])  # to the ends
    gs = np.where(t[:, None] > 0.1, 150.0, 30.0) + 0 * L
    kw = dict(gamma_dyn=70.0, gamma_stat=gs, backend=backend)
    whole = spindle.simulate(L, dt, chunk_samples=len(t), **kw)
    for size in (1, 7, 64):
        part = spindle.simulate(L, dt, chunk_samples=size, **kw)
        assert np.array_equal(part.ia, whole.ia) and np.array_equal(part.ii, whole.ii)
        assert part.substeps_limited == whole.substeps_limited
    assert np.array_equal(spindle.simulate(L, dt, **kw).ia, whole.ia)  # the default size


def test_chunk_samples_must_be_a_positive_count():
    with pytest.raises(ValueError, match="chunk_samples=0 must be an integer >= 1"):
        spindle.simulate(np.ones(5), 1e-3, chunk_samples=0)
    with pytest.raises(TypeError):
        spindle.simulate(np.ones(5), 1e-3, chunk_samples=2.5)


# -- memory on long inputs ------------------------------------------------------------------

MEMORY_CHILD = """
import resource, sys
import numpy as np
import spindle
n, backend = int(sys.argv[1]), sys.argv[2]
spindle.simulate(np.ones(3), 1e-3, backend=backend)  # imports and the C library loaded
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
L = np.arange(n, dtype=float)  # built in place: making it costs the input alone
L *= 2e-3 * np.pi * 0.5
np.sin(L, out=L)
L *= 0.2
L += 1.0
r = spindle.simulate(L, 1e-3, gamma_dyn=70.0, gamma_stat=70.0, backend=backend)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
assert np.isfinite(r.ia).all() and np.isfinite(r.ii).all()
print((peak - base) * 1024, L.nbytes, r.t_s.nbytes + r.ia.nbytes + r.ii.nbytes)
"""
MEMORY_OVERHEAD_B = 70e6
"""docs/spindle_accuracy.md: peak memory about input + output + 70 MB on long inputs."""


@pytest.mark.parametrize(("backend", "samples"), [
    pytest.param("c", 1_000_000, marks=needs_c),
    pytest.param("numpy", 1_000_000, marks=pytest.mark.slow),
])
def test_a_long_input_peaks_at_input_plus_output_plus_70_MB(backend, samples):
    """The growth of the peak RSS of a fresh process over 10^6 samples (15 chunks of the
    default size): measured (2026-12-02) C 39 MB for 8 MB in and 24 MB out (7 MB above
    them), numpy 10^5 samples 14 MB for 3 MB (11 MB above)."""
    repo = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(repo),
                                                        os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", MEMORY_CHILD, str(samples), backend],
                         capture_output=True, text=True, env=env, check=True).stdout
    growth, input_b, output_b = map(int, out.split())
    assert input_b == 8 * samples and output_b == 24 * samples
    assert growth <= input_b + output_b + MEMORY_OVERHEAD_B, growth / 1e6
    # and what is measured: before the streaming (6c9da6d) the C path took 45 MB above them
    assert growth - input_b - output_b < 20e6, growth / 1e6
