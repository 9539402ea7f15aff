"""ctypes binding of the C spindle (``c/spindle.c``) and the C path of ``simulate``.

The library is compiled on first use by :mod:`spindle.native.build` (a clear
:class:`~spindle.native.build.CBackendError` if no C compiler is found). :func:`simulate` is
``spindle.simulate(..., backend="c")``: the same validation and ValueErrors as the numpy path
(:func:`spindle.simulation.prepare_inputs`), the same sub-step lengths
(:func:`spindle.substeps.substep_lengths`), then one ``ps_spindle_run`` call per spindle.
:class:`CSpindleBatch` holds many independent spindles in one C array and advances them all by
one ``ps_spindle_batch_step`` call per step (the C counterpart of ``spindle.core.advance`` on
a :class:`~spindle.core.SpindleState`).
"""

from __future__ import annotations

import ctypes
from functools import cache

import numpy as np

from spindle.core import SpindleState, equilibrium_state
from spindle.methods import Method
from spindle.native import build
from spindle.native.abi import Status, params_struct, plan_struct, real_type, status_name, structs
from spindle.params import CAT, SpindleParams
from spindle.renamed import renamed_attribute
from spindle.simulation import SpindleResult, chunk_bounds, prepare_inputs
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
    # batches: arrays go as addresses (c_void_p), which costs a fraction of a microsecond per
    # argument against several for POINTER conversions
    vp = ctypes.c_void_p
    lib.ps_spindle_batch_step.argtypes = [vp, ctypes.c_long, P(PsPlan), vp, vp, vp, vp, vp, vp,
                                          P(ctypes.c_long)]
    lib.ps_spindle_batch_step.restype = ctypes.c_int
    lib.ps_spindle_batch_steps.argtypes = [vp, ctypes.c_long, ctypes.c_long, P(PsPlan), vp, vp,
                                           vp, vp, vp, vp, vp, P(ctypes.c_long),
                                           P(ctypes.c_long)]
    lib.ps_spindle_batch_steps.restype = ctypes.c_int
    lib.ps_spindle_batch_afferents.argtypes = [vp, ctypes.c_long, P(PsPlan), vp, vp]
    lib.ps_spindle_batch_afferents.restype = ctypes.c_int
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
    m, L, gd, gs, derivatives, k, h, dt = prepare_inputs(
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


STATE_FIELDS = (("tension_FU", 0, 3), ("polar_velocity_L0_s", 3, 6), ("velocity_root", 6, 9),
                ("activation", 9, 12), ("length_L0", 12, 13), ("gamma_dyn_pps", 13, 14),
                ("gamma_stat_pps", 14, 15))
""":class:`~spindle.core.SpindleState` attribute -> its columns in a ``ps_spindle`` row
(T[3], v[3], z[3], f[3], L, gd, gs)."""


class CSpindleBatch:
    """``n`` independent C spindles in one contiguous ``ps_spindle`` array, all with the same
    constants and step, advanced together by one ``ps_spindle_batch_step`` call per step
    (each spindle's step is ``ps_spindle_step_plan``, the C port's planned step).

    The state is read and written through :attr:`fields`, an (n, 15) numpy view of the C
    array (columns: :data:`STATE_FIELDS`); :meth:`load` and :meth:`state` convert from and to
    a :class:`spindle.core.SpindleState`.

    Args:
        state: the starting state (copied in), e.g. ``spindle.core.equilibrium_state(...)``.
        params: spindle constants.
        step_s: the step (s); :meth:`set_step` changes it.
        theta: the theta-method (0.5: trapezoidal).
        variant: ``"double"`` or ``"float"`` build.
    """

    def __init__(self, state: SpindleState, params: SpindleParams = CAT, step_s: float = 1e-3,
                 theta: float = 0.5, variant: str = "double") -> None:
        self.lib = library(variant)
        self.variant = variant
        self.dtype = _np_real(variant)
        self.n = int(state.n)
        self.theta = float(theta)
        self._params = params_struct(params, variant)
        self._plan = plan_struct(variant)()
        self.step_s = float("nan")
        self.set_step(step_s)
        _, PsSpindle = structs(variant)
        self._spindles = (PsSpindle * max(self.n, 1))()
        self._backup = (PsSpindle * max(self.n, 1))()
        self._address = ctypes.addressof(self._spindles)
        self._backup_address = ctypes.addressof(self._backup)
        self._start = (PsSpindle * max(self.n, 1))()
        self._start_address = ctypes.addressof(self._start)
        self._failed_step = ctypes.c_long()
        self.fields = np.frombuffer(self._spindles, dtype=self.dtype).reshape(-1, 15)[:self.n]
        self.ia_pps = np.zeros(self.n, dtype=self.dtype)
        self.ii_pps = np.zeros(self.n, dtype=self.dtype)
        self._failed = ctypes.c_long()
        # the per-call arguments that never change, made once: each ``.ctypes.data`` and
        # ``byref`` costs about a microsecond, a sixth of a legs env step's ctypes overhead
        self._rates_addresses = (self.ia_pps.ctypes.data, self.ii_pps.ctypes.data)
        self._plan_ref = ctypes.byref(self._plan)
        self._failed_refs = (ctypes.byref(self._failed_step), ctypes.byref(self._failed))
        self._stage: tuple[tuple[np.ndarray, ...], tuple[int, ...]] | None = None  # _staged
        self.load(state)

    def set_step(self, step_s: float) -> None:
        """Use steps of ``step_s`` seconds from now on (the plan is rebuilt if it changed)."""
        if step_s == self.step_s:
            return
        code = self.lib.ps_plan_init(ctypes.byref(self._plan), ctypes.byref(self._params),
                                     step_s, self.theta)
        if code != Status.PS_OK:
            raise ValueError(f"ps_plan_init refused step {step_s!r} s, theta {self.theta!r}: "
                             f"{status_name(code)}")
        self.step_s = float(step_s)

    def load(self, state: SpindleState, index: np.ndarray | None = None) -> None:
        """Write ``state`` into the spindles ``index`` (None: all; ``state.n`` must match)."""
        rows = self.fields if index is None else None
        for name, a, b in STATE_FIELDS:
            value = getattr(state, name)
            value = value if value.ndim == 2 else value[:, None]
            if rows is not None:
                rows[:, a:b] = value
            else:
                self.fields[np.asarray(index), a:b] = value

    def state(self) -> SpindleState:
        """A copy of the spindles' state as a :class:`spindle.core.SpindleState`."""
        out = equilibrium_state(np.ones(self.n))
        for name, a, b in STATE_FIELDS:
            column = self.fields[:, a:b].astype(float)
            getattr(out, name)[...] = column if b - a == 3 else column[:, 0]
        return out

    def step(self, length_L0: np.ndarray, gamma_dyn_pps: np.ndarray,
             gamma_stat_pps: np.ndarray, rates: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """One step of every spindle to the lengths and drives (n,) at its end.

        Returns (Ia, II) in pps, (n,) arrays owned by the batch (valid until the next call;
        not updated when ``rates`` is False). Atomic: on a failure every spindle is left as
        it was; FloatingPointError for a step that did not converge or went non-finite,
        ValueError for an input the C step refuses (out of range, too fast), each naming the
        spindle and the status.
        """
        arrays = self._inputs((length_L0, gamma_dyn_pps, gamma_stat_pps), 1)
        ia, ii = ((self.ia_pps.ctypes.data, self.ii_pps.ctypes.data) if rates
                  else (None, None))
        code = self.lib.ps_spindle_batch_step(
            self._address, self.n, ctypes.byref(self._plan), arrays[0].ctypes.data,
            arrays[1].ctypes.data, arrays[2].ctypes.data, self._backup_address, ia, ii,
            ctypes.byref(self._failed))
        if code != Status.PS_OK:
            self._raise(code, [x[None] for x in arrays], 0, "")
        return self.ia_pps, self.ii_pps

    def steps(self, length_L0: np.ndarray, gamma_dyn_pps: np.ndarray,
              gamma_stat_pps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`step` for each row of (steps, n) arrays, in one C call
        (``ps_spindle_batch_steps``); returns (Ia, II) of the last step (as :meth:`step`).
        Atomic over all the steps; the errors of :meth:`step`, naming the step too."""
        arrays = self._inputs((length_L0, gamma_dyn_pps, gamma_stat_pps), 2)
        shape = arrays[0].shape
        code = self.lib.ps_spindle_batch_steps(
            self._address, self.n, shape[0], self._plan_ref, *self._staged(arrays),
            self._start_address, self._backup_address, *self._rates_addresses,
            *self._failed_refs)
        if code != Status.PS_OK:
            self._raise(code, arrays, self._failed_step.value,
                        f" at step {self._failed_step.value} of {shape[0]}")
        return self.ia_pps, self.ii_pps

    def _staged(self, arrays: list[np.ndarray]) -> tuple[int, ...]:
        """The addresses of copies of ``arrays`` (validated by :meth:`_inputs`, one shape) in
        the batch's own input buffers, made once per shape: a copy of a legs env step's
        (10, 54) inputs costs a fifth of reading an array's ``.ctypes.data`` (~1 us, 26k of
        the step's instructions for three)."""
        shape = arrays[0].shape
        if self._stage is None or self._stage[0][0].shape != shape:
            buffers = tuple(np.empty(shape, self.dtype) for _ in arrays)
            self._stage = (buffers, tuple(b.ctypes.data for b in buffers))
        for buffer, x in zip(self._stage[0], arrays, strict=True):
            buffer[...] = x
        return self._stage[1]

    def _inputs(self, inputs: tuple, ndim: int) -> list[np.ndarray]:
        """The inputs as contiguous arrays of the build's type; ValueError unless all are
        (n,) (``ndim`` 1) or all (steps, n) of one shape (``ndim`` 2)."""
        arrays = [np.ascontiguousarray(x, dtype=self.dtype) for x in inputs]
        shape = arrays[0].shape
        if len(shape) != ndim or shape[-1] != self.n or any(x.shape != shape for x in arrays):
            expected = f"({self.n},)" if ndim == 1 else f"(steps, {self.n})"
            raise ValueError(f"inputs of shapes {[x.shape for x in arrays]} for {self.n} "
                             f"spindles; each must be {expected}")
        return arrays

    def _raise(self, code: int, arrays: list, step: int, where: str) -> None:
        j = self._failed.value
        message = (f"C spindle {j} of {self.n} failed{where} with {status_name(code)} (step "
                   f"{self.step_s!r} s); no spindle was advanced")
        # PS_ERR_NONFINITE is also a non-finite input: that one is the caller's error
        bad_input = not all(np.isfinite(x[step, j]) for x in arrays)
        if code == Status.PS_ERR_NO_CONVERGENCE or (code == Status.PS_ERR_NONFINITE
                                                    and not bad_input):
            raise FloatingPointError(message)
        raise ValueError(message)

    def afferents(self) -> tuple[np.ndarray, np.ndarray]:
        """(Ia, II) in pps of the current state, fresh (n,) arrays."""
        ia, ii = np.empty(self.n, self.dtype), np.empty(self.n, self.dtype)
        self.lib.ps_spindle_batch_afferents(self._address, self.n, ctypes.byref(self._plan),
                                            ia.ctypes.data, ii.ctypes.data)
        return ia, ii

_RENAMED = {"SpindleBatch": "CSpindleBatch"}  # renamed-from: the old names (spindle.renamed)


def __getattr__(name: str) -> object:
    return renamed_attribute(__name__, name, _RENAMED, globals())
