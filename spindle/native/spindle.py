"""ctypes binding of the C spindle (spindle/c/spindle.c) and the C path of ``simulate``.

The library is compiled on first use by :mod:`spindle.cbuild` (a clear
:class:`~spindle.cbuild.CBackendError` if no C compiler is found). :func:`simulate` is
``spindle.simulate(..., backend="c")``: the same validation and ValueErrors as the numpy path,
the same sub-step lengths (Hermite curves computed here with the numpy path's weights), then
one ``ps_spindle_run`` call per spindle.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from spindle import cbuild
from spindle.methods import Method
from spindle.params import CAT, SpindleParams

STATUS = {
    0: "PS_OK",
    1: "PS_ERR_NULL",
    2: "PS_ERR_NONFINITE",
    3: "PS_ERR_LENGTH_RANGE",
    4: "PS_ERR_NEGATIVE_DRIVE",
    5: "PS_ERR_STEP",
    6: "PS_ERR_SPEED",
    7: "PS_ERR_NO_CONVERGENCE",
    8: "PS_ERR_METHOD",
    9: "PS_ERR_CONFIG",
}
"""enum ps_status of proprio.h: value -> name."""

PS_OK = 0


@cache
def library(variant: str = "double", sanitize: bool = False) -> ctypes.CDLL:
    """The C library with the spindle functions' prototypes declared."""
    lib = cbuild.load(variant, sanitize)
    real = cbuild.real_type(variant)
    P = ctypes.POINTER
    PsParams, PsSpindle = cbuild.structs(variant)
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


# ps_plan of proprio.h, field by field in the header's order.
PLAN_SCALARS = ("h", "theta", "one_minus_theta", "th_h", "max_dL", "S")
PLAN_FLAGS = ("p_is_2", "a_is_03", "explicit_step", "uses_F0")
PLAN_FIBRE_FIELDS = (
    ("KSR", "inv_KSR", "c_f0", "c_a0", "c_a1", "c_a01"),
    ("freq_p", "p", "a", "beta0", "beta_drive", "Gamma_drive", "CL", "CS", "KPR", "LPR0", "R",
     "LSR0", "LSR0_R", "LSR0_LPR0", "h_KSR", "h_M", "c_Av", "a2", "inv_a2", "M_h", "th_h_KSR",
     "th_k1", "th_KPR", "th_CS", "th_dC", "stretch0", "G_pri", "c_sec1", "c_sec2", "sec_off"),
)


def plan_struct(variant: str = "double") -> type:
    """ctypes mirror of ``ps_plan`` (the embedded fast path's precomputed constants)."""
    if variant not in cbuild.VARIANTS:
        raise ValueError(f"variant={variant!r} is not one of {cbuild.VARIANTS}")
    return _plan_struct(variant)


@cache
def _plan_struct(variant: str) -> type:
    real = cbuild.real_type(variant)

    class PsPlan(ctypes.Structure):
        _fields_ = ([(name, real) for name in PLAN_SCALARS]
                    + [(name, ctypes.c_int) for name in PLAN_FLAGS]
                    + [(name, real * 3) for name in PLAN_FIBRE_FIELDS[0]]
                    + [("lagged", ctypes.c_int * 3)]
                    + [(name, real * 3) for name in PLAN_FIBRE_FIELDS[1]])

    return PsPlan


def status_name(code: int) -> str:
    return STATUS.get(code, f"unknown status {code}")


def _np_real(variant: str) -> type:
    return np.float32 if variant == "float" else np.float64


def _pointer(arr: np.ndarray, variant: str):
    return arr.ctypes.data_as(ctypes.POINTER(cbuild.real_type(variant)))


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
        self.p = cbuild.params_struct(params, variant)
        _, PsSpindle = cbuild.structs(variant)
        self.s = PsSpindle()
        self.steps_done = 0
        code = self.lib.ps_spindle_init(ctypes.byref(self.s), ctypes.byref(self.p), L, gd, gs)
        if code != PS_OK:
            raise ValueError(f"ps_spindle_init refused the first sample: {status_name(code)}")

    def afferents(self) -> tuple[float, float]:
        real = cbuild.real_type(self.variant)
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
        if code != PS_OK:
            message = (f"C spindle step {self.steps_done + done.value + 1} failed with "
                       f"{status_name(code)} (step {h_s!r} s, theta {theta!r})")
            if code in (2, 7):
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
    chunks and sub-step lengths as the numpy path (:func:`spindle.simulate.substep_lengths`),
    then one ``ps_spindle_run`` call per spindle and chunk."""
    from spindle.simulate import SpindleResult, chunk_bounds, prepare_inputs, substep_lengths

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
