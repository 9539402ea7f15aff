"""ctypes binding of the C spindle (``c/spindle.c``) and the C path of ``simulate``.

The library is compiled on first use by :mod:`spindle.native.build` (a clear
:class:`~spindle.native.build.CBackendError` if no C compiler is found). :func:`simulate` is
``spindle.simulate(..., backend="c")``: the same validation and ValueErrors as the numpy path
(:func:`spindle.simulate.prepare_inputs`), the same sub-step lengths
(:func:`spindle.substeps.substep_lengths`), then one ``ps_spindle_run`` call per spindle.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from spindle.methods import Method
from spindle.native import build
from spindle.native.abi import Status, params_struct, plan_struct, real_type, status_name, structs
from spindle.params import CAT, SpindleParams
from spindle.simulate import SpindleResult, chunk_bounds, prepare_inputs
from spindle.substeps import substep_lengths


@cache
def library(variant: str = "double", sanitize: bool = False) -> ctypes.CDLL:
    """The C library with the spindle functions' prototypes declared."""
    lib = build.load(variant, sanitize)
    real = real_type(variant)
    P = ctypes.POINTER
    PsParams, PsSpindle = structs(variant)
    ptr_real = P(real)
    lib.ps_spindle_init.argtypes = [P(PsSpindle), P(PsParams), real, real, real]
    lib.ps_spindle_init.restype = ctypes.c_int
    lib.ps_spindle_step.argtypes = [P(PsSpindle), P(PsParams), real, real, real, real, real,
                                    ptr_real, ptr_real]
    lib.ps_spindle_step.restype = ctypes.c_int
    lib.ps_spindle_afferents.argtypes = [P(PsSpindle), P(PsParams), ptr_real, ptr_real]
    lib.ps_spindle_afferents.restype = None
    lib.ps_params_check.argtypes = [P(PsParams)]
    lib.ps_params_check.restype = ctypes.c_int
    lib.ps_spindle_run.argtypes = [P(PsSpindle), P(PsParams), ptr_real, ptr_real, ptr_real,
                                   ctypes.c_long, real, real, ctypes.c_long, ptr_real,
                                   ptr_real, P(ctypes.c_long)]
    lib.ps_spindle_run.restype = ctypes.c_int
    PsPlan = plan_struct(variant)
    lib.ps_plan_init.argtypes = [P(PsPlan), P(PsParams), real, real]
    lib.ps_plan_init.restype = ctypes.c_int
    lib.ps_spindle_step_plan.argtypes = [P(PsSpindle), P(PsPlan), real, real, real, ptr_real,
                                         ptr_real]
    lib.ps_spindle_step_plan.restype = ctypes.c_int
    return lib


def _np_real(variant: str) -> type:
    return np.float32 if variant == "float" else np.float64


def _pointer(arr: np.ndarray, variant: str):
    return arr.ctypes.data_as(ctypes.POINTER(real_type(variant)))


def run_spindle(
    lengths_L0: np.ndarray,
    gamma_dyn_pps: np.ndarray,
    gamma_stat_pps: np.ndarray,
    h_s: float,
    theta: float,
    every: int,
    params: SpindleParams = CAT,
    variant: str = "double",
    sanitize: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """One spindle from rest at the first sample through the rest, in C.

    ``lengths_L0`` etc. are (1 + n_steps,) arrays: the start and the value at the end of
    every step. Returns (Ia, II) at the start and after every ``every``-th step. Raises
    FloatingPointError if a step fails (no convergence, non-finite result), ValueError for
    inputs the C code refuses.
    """
    dtype = _np_real(variant)
    L, gd, gs = (np.ascontiguousarray(x, dtype=dtype) for x in
                 (lengths_L0, gamma_dyn_pps, gamma_stat_pps))
    n_out = (L.shape[0] - 1) // every
    ia = np.empty(n_out + 1, dtype=dtype)
    ii = np.empty(n_out + 1, dtype=dtype)
    spindle = _CSpindle(L[0], gd[0], gs[0], params, variant, sanitize)
    ia[0], ii[0] = spindle.afferents()
    spindle.run(L[1:], gd[1:], gs[1:], h_s, theta, every, ia[1:], ii[1:])
    return ia, ii


class _CSpindle:
    """One C spindle (``ps_spindle``) at rest at (L, gd, gs), advanced run by run."""

    def __init__(self, L, gd, gs, params, variant, sanitize):
        self.lib = library(variant, sanitize)
        self.variant = variant
        self.dtype = _np_real(variant)
        self.p = params_struct(params, variant)
        _, PsSpindle = structs(variant)
        self.s = PsSpindle()
        self.steps_done = 0
        code = self.lib.ps_spindle_init(ctypes.byref(self.s), ctypes.byref(self.p), L, gd, gs)
        if code != Status.PS_OK:
            raise ValueError(f"ps_spindle_init refused the first sample: {status_name(code)}")

    def afferents(self) -> tuple[float, float]:
        real = real_type(self.variant)
        r_ia, r_ii = real(), real()
        self.lib.ps_spindle_afferents(ctypes.byref(self.s), ctypes.byref(self.p),
                                      ctypes.byref(r_ia), ctypes.byref(r_ii))
        return r_ia.value, r_ii.value

    def run(self, L, gd, gs, h_s, theta, every, ia, ii) -> None:
        """``ps_spindle_run`` through the contiguous arrays ``L``, ``gd``, ``gs`` (values at
        the end of each step), rates after every ``every``-th step into ``ia``, ``ii``."""
        variant = self.variant
        L, gd, gs = (np.ascontiguousarray(x, dtype=self.dtype) for x in (L, gd, gs))
        n_steps = L.shape[0]
        done = ctypes.c_long()
        code = self.lib.ps_spindle_run(
            ctypes.byref(self.s), ctypes.byref(self.p), _pointer(L, variant),
            _pointer(gd, variant), _pointer(gs, variant), n_steps, h_s, theta, every,
            _pointer(ia, variant), _pointer(ii, variant), ctypes.byref(done))
        if code != Status.PS_OK:
            message = (f"C spindle step {self.steps_done + done.value + 1} failed with "
                       f"{status_name(code)} (step {h_s!r} s, theta {theta!r})")
            if code in (Status.PS_ERR_NONFINITE, Status.PS_ERR_NO_CONVERGENCE):
                raise FloatingPointError(message)
            raise ValueError(message)
        self.steps_done += n_steps


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
    variant: str = "double",
    sanitize: bool = False,
    chunk_samples: int | None = None,
):
    """:func:`spindle.simulate` in C; ``variant="float"`` runs the float32 build. The same
    chunks and sub-step lengths as the numpy path (:func:`spindle.substeps.substep_lengths`),
    then one ``ps_spindle_run`` call per spindle and chunk."""
    m, L, gd, gs, derivatives, k, h = prepare_inputs(
        length, dt, velocity, acceleration, gamma_dyn, gamma_stat, method, step)
    shape = np.shape(length)
    n = L.shape[1]
    ia = np.empty_like(L)
    ii = np.empty_like(L)
    spindles = [_CSpindle(L[0, col], gd[0, col], gs[0, col], params, variant, sanitize)
                for col in range(n)]
    for col, spindle in enumerate(spindles):
        ia[0, col], ii[0, col] = spindle.afferents()
    limited = 0
    dtype = _np_real(variant)
    for i0, i1 in chunk_bounds(L.shape, k, chunk_samples):
        lengths, changed = substep_lengths(L, derivatives, k, dt, i0, i1)
        limited += changed
        out_ia = np.empty(i1 - i0, dtype=dtype)
        out_ii = np.empty(i1 - i0, dtype=dtype)
        for col, spindle in enumerate(spindles):
            spindle.run(lengths[:, col], np.repeat(gd[i0:i1, col], k),
                        np.repeat(gs[i0:i1, col], k), h, m.theta, k, out_ia, out_ii)
            ia[i0:i1, col] = out_ia
            ii[i0:i1, col] = out_ii
    t = np.arange(shape[0]) * dt
    return SpindleResult(t, ia.reshape(shape), ii.reshape(shape), m.name, h, limited)
