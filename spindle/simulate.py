"""Batch simulation of spindles driven by sampled fascicle-length traces.

Long inputs are streamed: the internal steps are built and run a chunk of sample intervals at
a time (:data:`CHUNK_ELEMENTS`), so memory stays a small multiple of the input and output;
the results do not depend on the chunk size (bit for bit).
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from spindle import core
from spindle.methods import Method, get_method
from spindle.params import CAT, SpindleParams


@dataclass(frozen=True)
class SpindleResult:
    """Afferent rates on the input's sample grid.

    Attributes:
        t_s: (T,) sample times, starting at 0.
        ia: primary (Ia) rate in pps, same shape as the input length.
        ii: secondary (II) rate in pps, same shape as the input length.
        method: the integration setting used; step_s: the internal step actually taken.
        substeps_limited: the number of internal-step lengths between samples that the
            interpolation rule moved back into the valid range or the speed limit (see
            :func:`substep_lengths`); 0 without sub-stepping.
    """

    t_s: np.ndarray
    ia: np.ndarray
    ii: np.ndarray
    method: str
    step_s: float
    substeps_limited: int = 0


MAX_SUBSTEPS = 100_000
"""Largest number of internal steps per sample interval (``dt`` / step). A larger ``dt`` (a
corrupted sample interval, say 1e9 s) is refused with ``ValueError`` before anything is
allocated, whatever the number of samples: the work per sample stays bounded."""

CHUNK_ELEMENTS = 1 << 16
"""Internal steps x spindles per chunk of a long input (the default of ``chunk_samples``)."""


def _broadcast_trace(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise ValueError(
            f"{name} has shape {arr.shape}, which does not broadcast to length's shape {shape}"
        ) from None


def substeps(dt_s: float, step_s: float) -> int:
    """Number of equal internal steps, each at most ``step_s``, that make up ``dt_s``."""
    return max(1, math.ceil(dt_s / step_s * (1 - 1e-12)))


class PreparedInputs(NamedTuple):
    """Checked inputs of :func:`simulate`, shared by its numpy and C paths.

    Attributes:
        method: the integration setting.
        L, gd, gs: (T, n) lengths and drives.
        derivatives: the derivative traces (T, n) that shape the length between samples.
        k: internal steps per sample interval; h: their length (s).
    """

    method: Method
    L: np.ndarray
    gd: np.ndarray
    gs: np.ndarray
    derivatives: list[np.ndarray]
    k: int
    h: float


def prepare_inputs(length, dt, velocity, acceleration, gamma_dyn, gamma_stat, method,
                   step) -> PreparedInputs:
    """Check and broadcast :func:`simulate`'s arguments (its Raises section applies)."""
    m = get_method(method)
    length = np.asarray(length, dtype=float)
    if length.ndim not in (1, 2) or length.shape[0] < 1:
        raise ValueError(f"length must have shape (T,) or (T, n), got {length.shape}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt={dt!r} s must be finite and > 0")
    h_max = m.default_step_s if step is None else float(step)
    core.check_step(h_max, m)
    k = substeps(dt, h_max)
    if k > MAX_SUBSTEPS:
        raise ValueError(
            f"dt={dt!r} s needs {float(k):.6g} internal steps of at most {h_max!r} s per "
            f"sample interval, above the limit MAX_SUBSTEPS = {MAX_SUBSTEPS}; resample the "
            "input or check its sample interval"
        )
    h = dt / k

    shape = length.shape
    L = length.reshape(shape[0], -1)
    gd = _broadcast_trace("gamma_dyn", gamma_dyn, shape).reshape(L.shape)
    gs = _broadcast_trace("gamma_stat", gamma_stat, shape).reshape(L.shape)
    core.check_inputs(L, gd, gs)
    core.check_speed(np.diff(L, axis=0), dt)
    derivatives = []
    if k > 1:
        if velocity is None:
            dL = np.gradient(L, dt, axis=0) if shape[0] > 1 else np.zeros_like(L)
        else:
            dL = _broadcast_trace("velocity", velocity, shape).reshape(L.shape)
        derivatives.append(dL)
        if acceleration is not None:
            derivatives.append(_broadcast_trace("acceleration", acceleration, shape)
                               .reshape(L.shape))
    else:
        derivatives = [
            _broadcast_trace(name, x, shape)
            for name, x in (("velocity", velocity), ("acceleration", acceleration))
            if x is not None
        ]
    for name, arr in zip(("velocity", "acceleration"), derivatives, strict=False):
        if not np.isfinite(arr).all():
            raise ValueError(f"{name} contains non-finite values; every value must be finite")

    return PreparedInputs(m, L, gd, gs, derivatives, k, h)


def simulate(
    length: np.ndarray,
    dt: float,
    *,
    velocity: np.ndarray | None = None,
    acceleration: np.ndarray | None = None,
    gamma_dyn: float | np.ndarray = 0.0,
    gamma_stat: float | np.ndarray = 0.0,
    params: SpindleParams = CAT,
    method: str | Method | None = None,
    step: float | None = None,
    backend: str = "numpy",
    chunk_samples: int | None = None,
) -> SpindleResult:
    """Ia and II rates of spindles whose host fascicles follow ``length``.

    Args:
        length: normalised fascicle length (L0) sampled every ``dt`` seconds, shape (T,) for
            one spindle or (T, n) for n spindles.
        dt: sample interval (s).
        velocity: dL/dt (L0/s) at the samples; if None, ``numpy.gradient`` of ``length``
            (second-order central differences).
        acceleration: d2L/dt2 (L0/s^2) at the samples, optional.
        gamma_dyn, gamma_stat: fusimotor drive (pps), scalars or arrays broadcastable to
            ``length``; held at each sample's value over the interval that ends there.
        params: spindle constants (:data:`spindle.CAT`, :data:`spindle.HUMAN`, ...).
        method: ``"trapezoidal"`` (default), ``"backward_euler"`` or ``"forward_euler"``.
        step: internal integration step (s). Each sample interval is split into the fewest
            equal sub-steps no longer than ``step``. None means the method's default.
        backend: ``"numpy"`` (default) or ``"c"``: the C port (spindle/c/spindle.c, compiled
            on first use; :class:`spindle.cbuild.CBackendError` if no C compiler is found).
            Both take the same inputs, raise the same ValueErrors and agree to 1e-6 pps
            (``docs/c_port.md``).
        chunk_samples: sample intervals per chunk of the stream (default: about
            :data:`CHUNK_ELEMENTS` internal steps x spindles); only memory depends on it.

    The integrator consumes lengths only (the (T, v) form integrates the dL/dt input exactly
    over a step, see :mod:`spindle.core`); the derivatives shape the length *between* samples
    when sub-stepping: a cubic Hermite curve through the samples and their velocities, or a
    quintic one when the acceleration is given too, held inside the valid range and the
    speed limit (:func:`substep_lengths`; the count is ``substeps_limited``). The spindles
    start at rest at the first sample's length and drive
    (:func:`spindle.core.equilibrium_state`).

    Raises:
        ValueError: non-finite inputs, lengths outside :data:`spindle.core.LENGTH_RANGE_L0`,
            length changes faster than :data:`spindle.core.MAX_SPEED_L0_S`, negative drive,
            ``dt`` or ``step`` <= 0 or above the method's limit, more than
            :data:`MAX_SUBSTEPS` internal steps per sample interval, shapes that do not
            match.
    """
    if backend == "c":
        from spindle import cbackend

        return cbackend.simulate(length, dt, velocity=velocity, acceleration=acceleration,
                                 gamma_dyn=gamma_dyn, gamma_stat=gamma_stat, params=params,
                                 method=method, step=step, chunk_samples=chunk_samples)
    if backend != "numpy":
        raise ValueError(f"backend={backend!r} is not one of ['c', 'numpy']")
    m, L, gd, gs, derivatives, k, h = prepare_inputs(
        length, dt, velocity, acceleration, gamma_dyn, gamma_stat, method, step)
    shape = np.shape(length)
    c = core.columns(params)
    state = core.equilibrium_state(L[0], gd[0], gs[0], params)
    ia = np.empty_like(L)
    ii = np.empty_like(L)
    ia[0], ii[0] = core._afferents(state.tension_FU.T, state.length_L0, c)
    one_spindle = L.shape[1] == 1 and m.implicit
    carry = _float_state(state) if one_spindle else None
    limited = 0
    for i0, i1 in chunk_bounds(L.shape, k, chunk_samples):
        lengths, changed = substep_lengths(L, derivatives, k, dt, i0, i1)
        limited += changed
        if one_spindle:
            carry = _run_one_spindle(carry, lengths, gd[i0:i1], gs[i0:i1], k, h, m.theta, c,
                                     ia[i0:i1], ii[i0:i1])
            continue
        for i in range(i0, i1):
            for j in range((i - i0) * k, (i - i0 + 1) * k):
                new = core.advance(state, lengths[j], gd[i], gs[i], h, m.theta, c)
                core.commit(state, new, lengths[j], gd[i], gs[i])
            ia[i], ii[i] = core._afferents(new[0], L[i], c)
    t = np.arange(shape[0]) * dt
    return SpindleResult(t, ia.reshape(shape), ii.reshape(shape), m.name, h, limited)


def chunk_bounds(shape: tuple[int, int], k: int, chunk_samples: int | None):
    """(i0, i1) of each chunk of sample intervals 1 .. T-1 (interval i ends on sample i)."""
    if chunk_samples is None:
        size = max(1, CHUNK_ELEMENTS // (k * max(shape[1], 1)))
    else:
        size = operator.index(chunk_samples)
        if size < 1:
            raise ValueError(f"chunk_samples={chunk_samples!r} must be >= 1")
    return [(i0, min(shape[0], i0 + size)) for i0 in range(1, shape[0], size)]


def _float_state(state: core.SpindleState) -> tuple:
    """One spindle's state as Python floats: (T, v, z, f) lists over fibres, L, gd, gs."""
    return (*(a[0].tolist() for a in (state.tension_FU, state.polar_velocity_L0_s,
                                      state.velocity_root, state.activation)),
            float(state.length_L0[0]), float(state.gamma_dyn_pps[0]),
            float(state.gamma_stat_pps[0]))


def _run_one_spindle(carry, lengths, gd, gs, k, h, theta, c, ia, ii):
    """The per-sample loop of one chunk for one spindle on Python floats (numpy's per-call
    overhead would dominate): the same step as the vectorised loop. ``carry`` is the state
    of :func:`_float_state`; returns the state after the chunk."""
    constants = core._step_constants(c, h, theta)
    steps = lengths[:, 0].tolist()
    T, v, z, f, L0, gd0, gs0 = carry
    rates_ia, rates_ii = [], []
    j = 0
    for gd1, gs1 in zip(gd[:, 0].tolist(), gs[:, 0].tolist(), strict=True):
        for L1 in steps[j:j + k]:
            T, v, z, f = core._step_floats(constants, T, v, z, f, L0, gd0, gs0, L1, gd1, gs1)
            L0, gd0, gs0 = L1, gd1, gs1
        j += k
        a, b = core._afferents_one(T, L0, c)
        rates_ia.append(a)
        rates_ii.append(b)
    ia[:, 0] = rates_ia
    ii[:, 0] = rates_ii
    return T, v, z, f, L0, gd0, gs0


def substep_lengths(L: np.ndarray, derivatives: list[np.ndarray], k: int, dt: float,
                    i0: int = 1, i1: int | None = None) -> tuple[np.ndarray, int]:
    """The length at the end of every internal step of sample intervals i0 .. i1-1 (interval
    i ends on sample i), shape ((i1 - i0)*k, n), and how many of them the limits changed.

    Sub-step j of an interval is the Hermite curve at fraction j/k (linear without
    ``derivatives``); step k ends on the sample itself. The curve can overshoot where valid
    samples lie near a range end or move near the speed limit, so each sub-step length is
    clipped to the valid range and to where it stays within MAX_SPEED_L0_S (less 1e-9, so
    that rounding never crosses the limit) both of the previous sub-step and of the sample
    that ends the interval: the clipped path is never faster than the limit and always lands
    on that sample. Inside those limits the curve is untouched (bit for bit). Both backends
    use these lengths.
    """
    i1 = L.shape[0] if i1 is None else i1
    start, end = L[i0 - 1:i1 - 1], L[i0:i1]
    out = np.empty((i1 - i0, k, L.shape[1]))
    out[:, k - 1] = end
    if k == 1:
        return out.reshape(-1, L.shape[1]), 0
    pairs = [(d[i0 - 1:i1 - 1], d[i0:i1]) for d in derivatives]
    lo_range, hi_range = core.LENGTH_RANGE_L0
    # each sub-step moves at most `reach`; samples that already move at the limit (within
    # the margin) keep their own pace, so that the band below never closes
    reach = np.maximum(core.MAX_SPEED_L0_S * (1.0 - 1e-9) * dt / k, np.abs(end - start) / k)
    previous = start
    changed = 0
    for j in range(1, k):
        w = hermite_weights(j / k, len(pairs))
        value = w[0] * start + w[1] * end
        scale = dt
        for q, (d0, d1) in enumerate(pairs):
            value = value + scale * (w[2 + 2 * q] * d0 + w[3 + 2 * q] * d1)
            scale *= dt
        left = reach * (k - j)  # what the remaining sub-steps can still cover
        lo = np.maximum(np.maximum(previous - reach, end - left), lo_range)
        hi = np.minimum(np.minimum(previous + reach, end + left), hi_range)
        clipped = np.minimum(np.maximum(value, lo), hi)
        changed += int(np.count_nonzero(clipped != value))
        out[:, j - 1] = clipped
        previous = clipped
    return out.reshape(-1, L.shape[1]), changed


def hermite_weights(s: float, order: int) -> np.ndarray:
    """Weights of (L0, L1, dt*v0, dt*v1, dt^2*a0, dt^2*a1) at fraction s of an interval.

    order 0: linear; 1: cubic Hermite (values and first derivatives); 2: quintic Hermite
    (values, first and second derivatives).
    """
    if order == 0:
        return np.array([1 - s, s])
    if order == 1:
        s2, s3 = s * s, s * s * s
        return np.array([2 * s3 - 3 * s2 + 1, -2 * s3 + 3 * s2, s3 - 2 * s2 + s, s3 - s2])
    s2, s3, s4, s5 = s**2, s**3, s**4, s**5
    return np.array([
        1 - 10 * s3 + 15 * s4 - 6 * s5,
        10 * s3 - 15 * s4 + 6 * s5,
        s - 6 * s3 + 8 * s4 - 3 * s5,
        -4 * s3 + 7 * s4 - 3 * s5,
        0.5 * (s2 - 3 * s3 + 3 * s4 - s5),
        0.5 * (s3 - 2 * s4 + s5),
    ])

