"""The fixed-point spindle step (``ps_spindle_step_fx``, int32 Q24) through ctypes.

The step is plain C99 in ``spindle.c``, so any host build of it (the cached library of
:mod:`spindle.native.build`, or the float32 twin of the Cortex-M0+ firmware in
:mod:`spindle.native.m0plus.build`) runs the same integers as the microcontroller. Lengths go
in as Q24 (L0), drives as Q8 (pps), rates come back as Q16 (pps): the scales of
``proprio.h`` (``PS_FX_ONE``, ``PS_FX_DRIVE_ONE``, ``PS_FX_RATE_ONE``).
"""

from __future__ import annotations

import ctypes

import numpy as np

from spindle.native import abi
from spindle.params import SpindleParams

FX_Q24 = 1 << 24
"""``PS_FX_ONE``: 1 L0 (and every other Q24 quantity) as an int32."""
FX_DRIVE = 256
"""``PS_FX_DRIVE_ONE``: 1 pps of fusimotor drive in Q8."""
FX_RATE = 1 << 16
"""``PS_FX_RATE_ONE``: 1 pps of Ia or II in Q16."""


def declare_fixed(lib: ctypes.CDLL, variant: str) -> None:
    """Prototypes of the fixed-point functions in a host build of ``spindle.c`` (``variant``:
    the ``ps_real`` of that build, which ``ps_plan_fx_init`` takes its constants in)."""
    PsPlanFx, PsSpindleFx = abi.fixed_structs()
    PsParams, _ = abi.structs(variant)
    P, i32 = ctypes.POINTER, ctypes.c_int32
    real = abi.real_type(variant)
    lib.ps_plan_fx_init.argtypes = [P(PsPlanFx), P(PsParams), real, real]
    lib.ps_spindle_fx_init.argtypes = [P(PsSpindleFx), P(PsPlanFx), i32, i32, i32]
    lib.ps_spindle_step_fx.argtypes = [P(PsSpindleFx), P(PsPlanFx), i32, i32, i32, P(i32),
                                       P(i32)]
    lib.ps_spindle_fx_afferents.argtypes = [P(PsSpindleFx), P(PsPlanFx), P(i32), P(i32)]
    lib.ps_spindle_fx_afferents.restype = None


def make_plan(lib: ctypes.CDLL, params: SpindleParams, step_s: float, theta: float,
              variant: str = "double") -> ctypes.Structure:
    """``ps_plan_fx_init`` of ``params`` at ``step_s``, ``theta``; raises on a refused plan."""
    PsPlanFx, _ = abi.fixed_structs()
    plan = PsPlanFx()
    code = lib.ps_plan_fx_init(ctypes.byref(plan),
                               ctypes.byref(abi.params_struct(params, variant)), step_s, theta)
    if code != abi.Status.PS_OK:
        raise RuntimeError(f"ps_plan_fx_init: {abi.status_name(code)}")
    return plan


def to_q(L: np.ndarray, gd: np.ndarray,
         gs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lengths (L0) in Q24 and drives (pps) in Q8, rounded to nearest, as int64 arrays of
    L's shape; ValueError for a value beyond int32 (the C step's own checks see the rest)."""
    L = np.asarray(L, dtype=np.float64)
    return (abi.checked_int32(np.round(L * FX_Q24), "L (Q24 L0)"),
            abi.checked_int32(np.round(np.broadcast_to(gd, L.shape) * FX_DRIVE), "gd (Q8 pps)"),
            abi.checked_int32(np.round(np.broadcast_to(gs, L.shape) * FX_DRIVE), "gs (Q8 pps)"))


def fixed_rates(lib: ctypes.CDLL, plan: ctypes.Structure, L: np.ndarray, gd: np.ndarray,
                gs: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Ia, II (pps) of the fixed-point step along L (L0), gd, gs (pps), starting at rest at
    L[0]; (ia, ii, status): on a failing step the rest is NaN and its status is returned."""
    _, PsSpindleFx = abi.fixed_structs()
    s = PsSpindleFx()
    q24, dgd, dgs = to_q(L, gd, gs)
    ia = np.full(len(q24), np.nan)
    ii = np.full(len(q24), np.nan)
    code = lib.ps_spindle_fx_init(ctypes.byref(s), ctypes.byref(plan), int(q24[0]),
                                  int(dgd[0]), int(dgs[0]))
    if code != abi.Status.PS_OK:
        return ia, ii, code
    a, b = ctypes.c_int32(), ctypes.c_int32()
    lib.ps_spindle_fx_afferents(ctypes.byref(s), ctypes.byref(plan), ctypes.byref(a),
                                ctypes.byref(b))
    ia[0], ii[0] = a.value / FX_RATE, b.value / FX_RATE
    for j in range(1, len(q24)):
        code = lib.ps_spindle_step_fx(ctypes.byref(s), ctypes.byref(plan), int(q24[j]),
                                      int(dgd[j]), int(dgs[j]), ctypes.byref(a),
                                      ctypes.byref(b))
        if code != abi.Status.PS_OK:
            return ia, ii, code
        ia[j], ii[j] = a.value / FX_RATE, b.value / FX_RATE
    return ia, ii, abi.Status.PS_OK
