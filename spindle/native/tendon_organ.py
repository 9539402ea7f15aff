"""ctypes binding of the C tendon organ (``c/tendon_organ.c``, ``proprio.h`` section 4).

:class:`CTendonOrgans` is the C twin of :class:`spindle.tendon_organ.TendonOrgans` (same
constructor, ``reset``, ``step``, ``rate_pps``, plus ``run`` for many steps in one call); the
same input rules, checked by the C code and reported here as the numpy path's ValueErrors.
:func:`fixed_rates` runs the fixed-point step (``ps_gto_step_fx``) along a force trace.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from spindle.native import build
from spindle.native.abi import INT32_MAX, Status, checked_int32, status_name
from spindle.tendon_organ_params import (
    HUMAN,
    MAX_FORCE_N,
    TendonOrganParams,
    check_force_scales,
    check_step,
)

FX_FORCE = 256
"""``PS_GTO_FX_FORCE_ONE``: 1 N in Q8."""
FX_RATE = 1 << 16
"""``PS_GTO_FX_RATE_ONE``: 1 pps in Q16."""
FX_INV_SCALE = 1 << 24
"""``PS_GTO_FX_INV_SCALE_ONE``: 1 / N in Q24."""
FX_MIN_FORCE_SCALE_N = FX_INV_SCALE / INT32_MAX
"""Smallest G2 the fixed-point step takes (~0.0078 N): 1/G2 in Q24 must fit an int32. Below
it ctypes wrapped the value silently (G2 = 0.0039 N gave the rates of G2 = 16,777 N)."""


def fixed_inv_scale(force_scale_N: float) -> int:
    """1 / G2 in Q24 for the fixed-point step, or ValueError naming G2 and the limit."""
    g = float(check_force_scales(force_scale_N))
    if g < FX_MIN_FORCE_SCALE_N:
        raise ValueError(f"force_scale_N={force_scale_N!r} is below the fixed-point step's "
                         f"FX_MIN_FORCE_SCALE_N={FX_MIN_FORCE_SCALE_N:.6g} N (1/G2 in Q24 "
                         "must fit an int32)")
    return round(FX_INV_SCALE / g)


def fixed_forces(force_N: object) -> np.ndarray:
    """Forces (N) in Q8 for the fixed-point step: finite and at most MAX_FORCE_N, else
    ValueError naming the first bad one; a negative force is a slack tendon, 0."""
    f = np.asarray(force_N, dtype=np.float64)
    bad = ~(np.isfinite(f) & (f <= MAX_FORCE_N))
    if np.any(bad):
        raise ValueError(f"force_N={f[bad][0]!r} must be finite and at most MAX_FORCE_N="
                         f"{MAX_FORCE_N} N (sample {int(np.flatnonzero(bad.ravel())[0])})")
    return checked_int32(np.round(np.maximum(f, 0.0) * FX_FORCE), "force_N (Q8 N)")


class PsGtoParams(ctypes.Structure):
    _fields_ = [("gain_pps", ctypes.c_double), ("tau_lowpass_s", ctypes.c_double),
                ("num", ctypes.c_double * 3), ("den", ctypes.c_double * 2)]


class PsGtoPlan(ctypes.Structure):
    _fields_ = [("phi", (ctypes.c_double * 3) * 3), ("g0", ctypes.c_double * 3),
                ("g1", ctypes.c_double * 3), ("c", ctypes.c_double * 3),
                ("gain_pps", ctypes.c_double), ("inv_a0", ctypes.c_double),
                ("h", ctypes.c_double)]


class PsGto(ctypes.Structure):
    _fields_ = [("z", ctypes.c_double * 3), ("force_N", ctypes.c_double),
                ("r_pps", ctypes.c_double)]


class PsGtoPlanFx(ctypes.Structure):
    _fields_ = [("phi", (ctypes.c_int32 * 3) * 3), ("g0", ctypes.c_int32 * 3),
                ("g1", ctypes.c_int32 * 3), ("c", ctypes.c_int32 * 3),
                ("gain", ctypes.c_int32), ("inv_a0", ctypes.c_int32)]


class PsGtoFx(ctypes.Structure):
    _fields_ = [("z", ctypes.c_int32 * 3), ("force", ctypes.c_int32), ("r", ctypes.c_int32)]


@cache
def library() -> ctypes.CDLL:
    """The (double) C library with the tendon organ's prototypes declared."""
    lib = build.load("double")
    P, d, i32, vp = ctypes.POINTER, ctypes.c_double, ctypes.c_int32, ctypes.c_void_p
    lib.ps_gto_plan_init.argtypes = [P(PsGtoPlan), P(PsGtoParams), d]
    lib.ps_gto_init.argtypes = [P(PsGto), P(PsGtoPlan), d, d]
    lib.ps_gto_step.argtypes = [P(PsGto), P(PsGtoPlan), d, d, P(d)]
    lib.ps_gto_rate.argtypes = [P(PsGto), P(PsGtoPlan)]
    lib.ps_gto_rate.restype = d
    lib.ps_gto_log1p.argtypes = [d]
    lib.ps_gto_log1p.restype = d
    lib.ps_gto_batch_run.argtypes = [vp, ctypes.c_long, P(PsGtoPlan), ctypes.c_long, vp, vp,
                                     vp, P(ctypes.c_long)]
    lib.ps_gto_plan_fx_init.argtypes = [P(PsGtoPlanFx), P(PsGtoPlan)]
    lib.ps_gto_fx_init.argtypes = [P(PsGtoFx), P(PsGtoPlanFx), i32, i32]
    lib.ps_gto_step_fx.argtypes = [P(PsGtoFx), P(PsGtoPlanFx), i32, i32, P(i32)]
    for name in ("ps_gto_plan_init", "ps_gto_init", "ps_gto_step", "ps_gto_batch_run",
                 "ps_gto_plan_fx_init", "ps_gto_fx_init", "ps_gto_step_fx"):
        getattr(lib, name).restype = ctypes.c_int
    return lib


def params_struct(params: TendonOrganParams) -> PsGtoParams:
    out = PsGtoParams(params.gain_pps, params.tau_lowpass_s)
    out.num[:] = list(params.num)
    out.den[:] = list(params.den)
    return out


def c_plan(params: TendonOrganParams, dt_s: float) -> PsGtoPlan:
    """``ps_gto_plan_init`` of ``params`` at ``dt_s`` (the numpy rules checked first)."""
    h = check_step(dt_s)
    q = PsGtoPlan()
    code = library().ps_gto_plan_init(ctypes.byref(q), ctypes.byref(params_struct(params)), h)
    if code != Status.PS_OK:
        raise ValueError(f"ps_gto_plan_init refused params={params!r}, dt_s={dt_s!r}: "
                         f"{status_name(code)}")
    return q


def _raise_for(code: int, forces: np.ndarray, where: int) -> None:
    value = forces.reshape(-1)[where] if 0 <= where < forces.size else None
    if code == Status.PS_ERR_NONFINITE:
        raise ValueError(f"force_N={value!r} is not finite (flat index {where})")
    if code == Status.PS_ERR_FORCE_RANGE:
        raise ValueError(f"force_N={value!r} exceeds MAX_FORCE_N={MAX_FORCE_N} N "
                         f"(flat index {where})")
    raise ValueError(f"ps_gto: {status_name(code)}")


class CTendonOrgans:
    """n tendon organs in one C array, stepped by one ``ps_gto_batch_run`` call."""

    backend = "c"

    def __init__(self, force_scale_N: object, params: TendonOrganParams = HUMAN,
                 dt_s: float = 1e-3, force_N: object = 0.0) -> None:
        g = np.atleast_1d(np.asarray(force_scale_N, dtype=np.float64))
        if g.ndim != 1:
            raise ValueError(f"force_scale_N has shape {g.shape}; expected a scalar or (n,)")
        g = np.ascontiguousarray(check_force_scales(g))
        self.params = params
        self.force_scale_N = g
        self._plans: dict[float, PsGtoPlan] = {}
        self.dt_s = check_step(dt_s)
        self.plan = self._plan(self.dt_s)
        self._states = (PsGto * g.shape[0])()
        self.reset(force_N)

    @property
    def n(self) -> int:
        return self.force_scale_N.shape[0]

    def _plan(self, dt_s: float) -> PsGtoPlan:
        if dt_s not in self._plans:
            if len(self._plans) >= 64:
                self._plans.clear()
            self._plans[dt_s] = c_plan(self.params, dt_s)
        return self._plans[dt_s]

    def _forces(self, force_N: object, rows: int) -> np.ndarray:
        f = np.asarray(force_N, dtype=np.float64)
        try:
            return np.ascontiguousarray(np.broadcast_to(f, (rows, self.n)) if rows > 1
                                        else np.broadcast_to(f, (self.n,)))
        except ValueError:
            raise ValueError(f"force_N has shape {f.shape}; expected a scalar or "
                             f"({self.n},)") from None

    def reset(self, force_N: object = 0.0, rows: np.ndarray | None = None) -> np.ndarray:
        """At rest at ``force_N``; returns the rates there. With ``rows`` (organ indices),
        only those organs, ``force_N`` then a scalar or one per row. Nothing changes on a bad
        force."""
        which = np.arange(self.n) if rows is None else np.asarray(rows, dtype=np.intp)
        f = np.asarray(force_N, dtype=np.float64)
        try:
            f = np.ascontiguousarray(np.broadcast_to(f, which.shape))
        except ValueError:
            raise ValueError(f"force_N has shape {f.shape}; expected a scalar or "
                             f"({which.size},)") from None
        lib, fresh = library(), (PsGto * which.size)()
        for j, i in enumerate(which.tolist()):
            code = lib.ps_gto_init(ctypes.byref(fresh[j]), ctypes.byref(self.plan), f[j],
                                   self.force_scale_N[i])
            if code != Status.PS_OK:
                _raise_for(code, f, j)
        if rows is None:
            self._states = fresh
        else:
            for j, i in enumerate(which.tolist()):
                self._states[i] = fresh[j]
        return self.rate_pps()

    def run(self, force_N: np.ndarray, dt_s: float | None = None,
            first: bool = False) -> np.ndarray:
        """Steps to each row of ``force_N`` ((steps, n)); Ib after each, (steps, n), with the
        rates at the start as an extra first row if ``first``. Atomic: a bad force anywhere
        raises before any step."""
        q = self.plan if dt_s is None else self._plan(check_step(dt_s))
        f = np.ascontiguousarray(np.asarray(force_N, dtype=np.float64).reshape(-1, self.n))
        out = np.empty((f.shape[0] + int(first), self.n))
        if first:
            out[0] = self.rate_pps()
        failed = ctypes.c_long(-1)
        code = library().ps_gto_batch_run(
            ctypes.addressof(self._states), self.n, ctypes.byref(q), f.shape[0],
            f.ctypes.data, self.force_scale_N.ctypes.data, out[int(first):].ctypes.data,
            ctypes.byref(failed))
        if code != Status.PS_OK:
            _raise_for(code, f, failed.value)
        return out

    def step(self, force_N: object, dt_s: float | None = None) -> np.ndarray:
        """One step to ``force_N`` (scalar or (n,)); Ib (pps, (n,))."""
        return self.run(self._forces(force_N, 1)[None, :], dt_s)[0]

    def rate_pps(self) -> np.ndarray:
        lib = library()
        return np.array([lib.ps_gto_rate(ctypes.byref(s), ctypes.byref(self.plan))
                         for s in self._states])

    def rows_state(self, rows: np.ndarray) -> list[bytes]:
        """The states of organs ``rows`` as bytes (for :meth:`set_rows_state`)."""
        return [bytes(self._states[i]) for i in np.asarray(rows, dtype=np.intp).tolist()]

    def set_rows_state(self, rows: np.ndarray, saved: list[bytes]) -> np.ndarray:
        """Organs ``rows`` back to ``saved`` (:meth:`rows_state`); returns every rate."""
        for i, raw in zip(np.asarray(rows, dtype=np.intp).tolist(), saved, strict=True):
            self._states[i] = PsGto.from_buffer_copy(raw)
        return self.rate_pps()

    def __getstate__(self) -> dict[str, object]:
        """Copies and pickles: the states travel as their bytes, the plans are made again
        (ctypes arrays of structs do not pickle)."""
        state = {k: v for k, v in self.__dict__.items() if k not in ("_states", "_plans",
                                                                      "plan")}
        state["_state_bytes"] = bytes(self._states)
        return state

    def __setstate__(self, state: dict[str, object]) -> None:
        raw = state.pop("_state_bytes")
        self.__dict__.update(state)
        self._plans = {}
        self.plan = self._plan(self.dt_s)
        self._states = (PsGto * self.n).from_buffer_copy(raw)

    def state_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(z (3, n), force_N (n,), r_pps (n,)) copied out of the C states."""
        z = np.array([list(s.z) for s in self._states]).T
        return (z, np.array([s.force_N for s in self._states]),
                np.array([s.r_pps for s in self._states]))


def fixed_plan(params: TendonOrganParams, dt_s: float) -> PsGtoPlanFx:
    """``ps_gto_plan_fx_init`` from the double plan; ValueError if it is refused."""
    qf = PsGtoPlanFx()
    code = library().ps_gto_plan_fx_init(ctypes.byref(qf), ctypes.byref(c_plan(params, dt_s)))
    if code != Status.PS_OK:
        raise ValueError(f"ps_gto_plan_fx_init refused params={params!r}: {status_name(code)}")
    return qf


def fixed_rates(force_N: np.ndarray, dt_s: float, force_scale_N: float,
                params: TendonOrganParams = HUMAN) -> np.ndarray:
    """Ib (pps) of the fixed-point step along one force trace ((T,), N), from rest at the
    first sample: forces rounded to Q8, 1/G2 to Q24, rates read from Q16."""
    lib, qf, s = library(), fixed_plan(params, dt_s), PsGtoFx()
    q8 = fixed_forces(force_N)
    inv = fixed_inv_scale(force_scale_N)
    out = np.empty(q8.shape[0])
    code = lib.ps_gto_fx_init(ctypes.byref(s), ctypes.byref(qf), int(q8[0]), inv)
    if code != Status.PS_OK:
        raise ValueError(f"ps_gto_fx_init: {status_name(code)}")
    ib = ctypes.c_int32()
    y = (qf.c[0] * s.z[0] + qf.c[1] * s.z[1] + qf.c[2] * s.z[2]) / (1 << 30)
    out[0] = max(y, 0.0) / FX_RATE
    for k in range(1, q8.shape[0]):
        code = lib.ps_gto_step_fx(ctypes.byref(s), ctypes.byref(qf), int(q8[k]), inv,
                                  ctypes.byref(ib))
        if code != Status.PS_OK:
            raise ValueError(f"ps_gto_step_fx at sample {k}: {status_name(code)}")
        out[k] = ib.value / FX_RATE
    return out
