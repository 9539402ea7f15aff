"""Batch simulation of spindles driven by sampled fascicle-length traces (numpy).

The public entry point is :func:`spindle.simulate` (``spindle/__init__.py``), which runs this
module's :func:`simulate` or, with ``backend="c"``, :func:`spindle.native.spindle.simulate`;
both share :func:`prepare_inputs`, :func:`chunk_bounds` and the sub-step lengths of
:mod:`spindle.substeps`.

Long inputs are streamed: the internal steps are built and run a chunk of sample intervals at
a time (:data:`CHUNK_ELEMENTS`), so memory stays a small multiple of the input and output;
the results do not depend on the chunk size (bit for bit).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from spindle import core
from spindle.fibre_constants import step_constants
from spindle.float_step import afferents_one, step_floats
from spindle.methods import Method, get_method
from spindle.number_rule import positive_int, real_array, real_scalar
from spindle.params import CAT, SpindleParams
from spindle.substeps import substep_lengths, substeps


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
    arr = real_array(name, value)
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise ValueError(
            f"{name} has shape {arr.shape}, which does not broadcast to length's shape {shape}"
        ) from None


class PreparedInputs(NamedTuple):
    """Checked inputs of :func:`simulate`, shared by its numpy and C paths.

    Attributes:
        method: the integration setting.
        L, gd, gs: (T, n) lengths and drives.
        derivatives: the derivative traces (T, n) that shape the length between samples.
        k: internal steps per sample interval; h: their length (s).
        dt: the sample interval (s), a Python float.
    """

    method: Method
    L: np.ndarray
    gd: np.ndarray
    gs: np.ndarray
    derivatives: list[np.ndarray]
    k: int
    h: float
    dt: float


def prepare_inputs(length, dt, velocity, acceleration, gamma_dyn, gamma_stat, method,
                   step) -> PreparedInputs:
    """Check and broadcast :func:`simulate`'s arguments (its Raises section applies)."""
    m = get_method(method)
    # spindle.number_rule: no bool, string, bytes or complex taken as a number, and every
    # number a Python float / float64 before anything (the step constants' cache) keeps it
    length = real_array("length", length)
    if length.ndim not in (1, 2) or length.shape[0] < 1:
        raise ValueError(f"length must have shape (T,) or (T, n), got {length.shape}")
    dt = real_scalar("dt", dt, low=0.0, low_open=True)
    h_max = core.check_step(m.default_step_s if step is None else step, m)
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

    return PreparedInputs(m, L, gd, gs, derivatives, k, h, dt)


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
    chunk_samples: int | None = None,
) -> SpindleResult:
    """The numpy path of :func:`spindle.simulate` (the package's function, which also takes
    ``backend``): the same arguments, results and errors, as documented there."""
    m, L, gd, gs, derivatives, k, h, dt = prepare_inputs(
        length, dt, velocity, acceleration, gamma_dyn, gamma_stat, method, step)
    shape = np.shape(length)
    c = core.columns(params)
    state = core.equilibrium_state(L[0], gd[0], gs[0], params)
    ia = np.empty_like(L)
    ii = np.empty_like(L)
    ia[0], ii[0] = core.afferents_from_tension(state.tension_FU.T, state.length_L0, c)
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
            ia[i], ii[i] = core.afferents_from_tension(new[0], L[i], c)
    t = np.arange(shape[0]) * dt
    return SpindleResult(t, ia.reshape(shape), ii.reshape(shape), m.name, h, limited)


def chunk_bounds(shape: tuple[int, int], k: int, chunk_samples: int | None):
    """(i0, i1) of each chunk of sample intervals 1 .. T-1 (interval i ends on sample i)."""
    if chunk_samples is None:
        size = max(1, CHUNK_ELEMENTS // (k * max(shape[1], 1)))
    else:
        size = positive_int("chunk_samples", chunk_samples)
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
    constants = step_constants(c, h, theta)
    steps = lengths[:, 0].tolist()
    T, v, z, f, L0, gd0, gs0 = carry
    rates_ia, rates_ii = [], []
    j = 0
    for gd1, gs1 in zip(gd[:, 0].tolist(), gs[:, 0].tolist(), strict=True):
        for L1 in steps[j:j + k]:
            T, v, z, f = step_floats(constants, T, v, z, f, L0, gd0, gs0, L1, gd1, gs1)
            L0, gd0, gs0 = L1, gd1, gs1
        j += k
        a, b = afferents_one(T, L0, c)
        rates_ia.append(a)
        rates_ii.append(b)
    ia[:, 0] = rates_ia
    ii[:, 0] = rates_ii
    return T, v, z, f, L0, gd0, gs0
