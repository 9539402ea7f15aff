"""Batch simulation of spindles driven by sampled fascicle-length traces."""

from __future__ import annotations

import math
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
    """

    t_s: np.ndarray
    ia: np.ndarray
    ii: np.ndarray
    method: str
    step_s: float


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

    The integrator consumes lengths only (the (T, v) form integrates the dL/dt input exactly
    over a step, see :mod:`spindle.core`); the derivatives shape the length *between* samples
    when sub-stepping: a cubic Hermite curve through the samples and their velocities, or a
    quintic one when the acceleration is given too. The spindles start at rest at the first
    sample's length and drive (:func:`spindle.core.equilibrium_state`).

    Raises:
        ValueError: non-finite inputs, lengths outside :data:`spindle.core.LENGTH_RANGE_L0`,
            length changes faster than :data:`spindle.core.MAX_SPEED_L0_S`, negative drive,
            ``dt`` or ``step`` <= 0 or above the method's limit, shapes that do not match.
    """
    if backend == "c":
        from spindle import cbackend

        return cbackend.simulate(length, dt, velocity=velocity, acceleration=acceleration,
                                 gamma_dyn=gamma_dyn, gamma_stat=gamma_stat, params=params,
                                 method=method, step=step)
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
    weights = [hermite_weights(j / k, len(derivatives) if k > 1 else 0) for j in range(1, k)]
    if L.shape[1] == 1 and m.implicit:
        _run_one_spindle(state, L, gd, gs, derivatives, weights, dt, h, m.theta, c, ia, ii)
    else:
        for i in range(1, L.shape[0]):
            for wts in weights:
                Ls = _interpolate(L, derivatives, i, wts, dt)
                core.commit(state, core.advance(state, Ls, gd[i], gs[i], h, m.theta, c),
                            Ls, gd[i], gs[i])
            new = core.advance(state, L[i], gd[i], gs[i], h, m.theta, c)
            core.commit(state, new, L[i], gd[i], gs[i])
            ia[i], ii[i] = core._afferents(new[0], L[i], c)
    t = np.arange(shape[0]) * dt
    return SpindleResult(t, ia.reshape(shape), ii.reshape(shape), m.name, h)


def _run_one_spindle(state, L, gd, gs, derivatives, weights, dt, h, theta, c, ia, ii):
    """The per-sample loop for one spindle on Python floats (numpy's per-call overhead would
    dominate): the same interpolation and the same step as the vectorised loop."""
    k = core._step_constants(c, h, theta)
    lengths, dyn, stat = (x[:, 0].tolist() for x in (L, gd, gs))
    derivs = [np.reshape(d, L.shape)[:, 0].tolist() for d in derivatives] if weights else []
    weights = [w.tolist() for w in weights]
    T, v, z, f = (a[0].tolist() for a in (state.tension_FU, state.polar_velocity_L0_s,
                                          state.velocity_root, state.activation))
    L0, gd0, gs0 = lengths[0], dyn[0], stat[0]
    rates_ia, rates_ii = [], []
    for i in range(1, len(lengths)):
        gd1, gs1 = dyn[i], stat[i]
        for wts in weights:
            Ls = wts[0] * lengths[i - 1] + wts[1] * lengths[i]
            scale = dt
            for j, d in enumerate(derivs):
                Ls = Ls + scale * (wts[2 + 2 * j] * d[i - 1] + wts[3 + 2 * j] * d[i])
                scale *= dt
            T, v, z, f = core._step_floats(k, T, v, z, f, L0, gd0, gs0, Ls, gd1, gs1)
            L0, gd0, gs0 = Ls, gd1, gs1
        L1 = lengths[i]
        T, v, z, f = core._step_floats(k, T, v, z, f, L0, gd0, gs0, L1, gd1, gs1)
        L0, gd0, gs0 = L1, gd1, gs1
        a, b = core._afferents_one(T, L1, c)
        rates_ia.append(a)
        rates_ii.append(b)
    ia[1:, 0] = rates_ia
    ii[1:, 0] = rates_ii


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


def _interpolate(L, derivatives, i, weights, dt):
    out = weights[0] * L[i - 1] + weights[1] * L[i]
    scale = dt
    for j, d in enumerate(derivatives):
        out = out + scale * (weights[2 + 2 * j] * d[i - 1] + weights[3 + 2 * j] * d[i])
        scale *= dt
    return out
