"""Muscle-spindle afferents for artificial proprioception.

The Mileusnic et al. (2006) spindle with cat and human (seed paper: G x 1/5) presets,
integrated by a theta-method (forward Euler, backward Euler, trapezoidal rule), and a stiff
reference solver (scipy, optional) to check it against. The package's rooms:

- the receptor model (numpy only): :mod:`spindle.params`, :mod:`spindle.methods`,
  :mod:`spindle.core` (the step), :mod:`spindle.substeps`, :mod:`spindle.simulation`,
  :mod:`spindle.reference`;
- :mod:`spindle.chain`: what runs on the prosthesis (sensor, length model, conditioning,
  fusimotor, the arm chain);
- :mod:`spindle.native`: the C port and its one binding layer.

This module is the public facade: :func:`simulate` picks the numpy or the C path.
"""

from __future__ import annotations

import numpy as np

from spindle.backends import DEFAULT_BACKEND, implementation
from spindle.chain.length_model import (
    LengthFit,
    LengthFits,
    LengthFitsError,
    default_fits_path,
    load_length_fits,
)
from spindle.core import (
    LENGTH_RANGE_L0,
    MAX_SPEED_L0_S,
    SpindleState,
    afferents,
    equilibrium_state,
    step,
)
from spindle.methods import DEFAULT_METHOD, METHODS, Method, get_method
from spindle.params import CAT, FIBRES, HUMAN, FibreParams, SpindleParams
from spindle.simulation import SpindleResult

__all__ = [
    "CAT",
    "DEFAULT_METHOD",
    "FIBRES",
    "HUMAN",
    "LENGTH_RANGE_L0",
    "MAX_SPEED_L0_S",
    "METHODS",
    "FibreParams",
    "LengthFit",
    "LengthFits",
    "LengthFitsError",
    "Method",
    "SpindleParams",
    "SpindleResult",
    "SpindleState",
    "afferents",
    "default_fits_path",
    "equilibrium_state",
    "get_method",
    "load_length_fits",
    "simulate",
    "step",
]

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
    backend: str = DEFAULT_BACKEND,
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
        backend: ``"numpy"`` (:mod:`spindle.simulation`), ``"c"`` (the C port,
            ``spindle/native/c/spindle.c`` through :mod:`spindle.native.spindle`, compiled on
            first use; :class:`spindle.native.build.CBackendError` if no C compiler is found)
            or ``"auto"`` (the default: C where the library loads or builds here, else numpy;
            :func:`spindle.backends.resolve_backend`). Both take the same inputs, raise the
            same ValueErrors and agree to ~1e-12 pps for the implicit methods
            (``docs/c_port.md``).
        chunk_samples: sample intervals per chunk of the stream (default: about
            :data:`spindle.simulation.CHUNK_ELEMENTS` internal steps x spindles); only memory
            depends on it.

    The integrator consumes lengths only (the (T, v) form integrates the dL/dt input exactly
    over a step, see :mod:`spindle.core`); the derivatives shape the length *between* samples
    when sub-stepping: a cubic Hermite curve through the samples and their velocities, or a
    quintic one when the acceleration is given too, held inside the valid range and the
    speed limit (:func:`spindle.substeps.substep_lengths`; the count is
    ``substeps_limited``). The spindles start at rest at the first sample's length and drive
    (:func:`spindle.core.equilibrium_state`).

    Raises:
        ValueError: non-finite inputs, lengths outside :data:`spindle.core.LENGTH_RANGE_L0`,
            length changes faster than :data:`spindle.core.MAX_SPEED_L0_S`, negative drive,
            ``dt`` or ``step`` <= 0 or above the method's limit, more than
            :data:`spindle.simulation.MAX_SUBSTEPS` internal steps per sample interval, shapes
            that do not match; :class:`spindle.number_rule.NumberError` (a ValueError and a
            TypeError) for a bool, string, bytes, complex or None where a number belongs
            (``dt=True``, string or complex lengths).
    """
    _, run = implementation("simulate", backend)
    return run(length, dt, velocity=velocity, acceleration=acceleration, gamma_dyn=gamma_dyn,
               gamma_stat=gamma_stat, params=params, method=method, step=step,
               chunk_samples=chunk_samples)
