"""The spindle's constants in the shapes the step uses, and the implicit step's settings.

:func:`columns` gives a parameter set's fibre constants as (3, 1) columns (rows bag1, bag2,
chain) that broadcast against the fibre-major (3, n) working arrays; :func:`step_constants`
gives, per fibre, the constants of one implicit step of size h and weight theta
(:class:`FibreStepConstants`), which both fast implementations of the step
(:mod:`spindle.batch_step` and :mod:`spindle.float_step`) read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from spindle.params import FibreParams, SpindleParams

NEWTON_MAX_ITER = 60
NEWTON_FULL_ITER = 3
NEWTON_TOL_Z = 1e-9
NEWTON_MAX_DZ = 0.25

MAX_DRIVE_POWER = float(np.finfo(float).max)
"""g^p is capped here: a drive so large that g^p overflows (g > 1.3e154 pps for p = 2) has
activation exactly 1 (g^p / (g^p + freq^p) rounds to 1 long before), as in the C port,
instead of inf/inf = NaN."""


class FibreColumns:
    """Fibre constants as (3, 1) columns, computed once per parameter set."""

    def __init__(self, params: SpindleParams):
        col = params.column
        self.KSR = col("KSR_FU_L0")
        self.KPR = col("KPR_FU_L0")
        self.M = col("M_FU_s2_L0")
        self.beta0 = col("beta0_FU_s_L0")
        self.beta_drive = col("beta_drive_FU_s_L0")
        self.Gamma_drive = col("Gamma_drive_FU")
        self.CL = col("CL")
        self.CS = col("CS")
        self.R = col("R_L0")
        self.a = col("a")
        self.LSR0 = col("LSR0_L0")
        self.LPR0 = col("LPR0_L0")
        self.freq = col("freq_pps")
        self.p = col("p")
        self.tau = col("tau_s")
        self.lagged = self.tau[:, 0] > 0
        self.tau_safe = np.where(self.tau > 0, self.tau, 1.0)
        self.k1 = 1.0 + self.KPR / self.KSR
        # With a = 0.3, v = z^10 * sgn(z): a polynomial, many times cheaper than a power.
        self.a_is_03 = bool(np.all(self.a == 0.3))
        self.step_constants: StepConstants | None = None
        self.spindle_step_constants: SpindleStepConstants | None = None
        self.per_spindle_coefficients: _Coefficients | None = None
        self.fibre_params = params.fibres
        self.fibre_parameter_columns = _ParameterColumns(params)
        self.S = float(params.S)
        self.primary_lin = tuple(_primary_linear(f) for f in params.fibres)
        self.secondary_lin = tuple(_secondary_linear(f) for f in params.fibres[1:])


def _primary_linear(f: FibreParams) -> tuple[float, float]:
    """(g, n) with the primary potential G*(T/KSR - (LNSR - LSR0)) = T*g - n."""
    return f.G_primary_pps_L0 / f.KSR_FU_L0, f.G_primary_pps_L0 * (f.LNSR_L0 - f.LSR0_L0)


def _secondary_linear(f: FibreParams) -> tuple[float, float, float]:
    """(a, b, c) with the secondary potential G2*(X*Lsec/LSR0*(T/KSR - (LNSR - LSR0))
    + (1 - X)*Lsec/LPR0*(L - T/KSR - LSR0 - LNPR)) = T*a + L*b + c."""
    G2, X, Lsec = f.G_secondary_pps_L0, f.X, f.Lsec_L0
    return (G2 * (X * Lsec / f.LSR0_L0 - (1.0 - X) * Lsec / f.LPR0_L0) / f.KSR_FU_L0,
            G2 * (1.0 - X) * Lsec / f.LPR0_L0,
            -G2 * (X * Lsec / f.LSR0_L0 * (f.LNSR_L0 - f.LSR0_L0)
                   + (1.0 - X) * Lsec / f.LPR0_L0 * (f.LSR0_L0 + f.LNPR_L0)))


_COLUMNS_CACHE: dict[int, tuple[SpindleParams, FibreColumns]] = {}


def columns(params: SpindleParams) -> FibreColumns:
    """The :class:`FibreColumns` of ``params`` (cached by identity)."""
    key = id(params)
    hit = _COLUMNS_CACHE.get(key)
    if hit is None or hit[0] is not params:
        hit = (params, FibreColumns(params))
        if len(_COLUMNS_CACHE) > 64:
            _COLUMNS_CACHE.clear()
        _COLUMNS_CACHE[key] = hit
    return hit[1]


@dataclass(frozen=True, slots=True)
class FibreStepConstants:
    """One fibre's constants of one implicit step (floats, or (3, 1) columns of all three).

    The theta-method's equation for the new z (see :func:`spindle.batch_step.newton_loop`)
    needs, from the start of the step, with q0 = L0 - LSR0 - R - T0/KSR (the polar length
    minus R):

        A   = T0 + KSR*(L1 - L0) - (1 - theta)*h*KSR*v0          (T1 = A - theta*h*KSR*v1)
        p0  = q0 + (1 - theta)*h*v0                               (= L1 - LSR0 - R - A/KSR)
        rhs = (M/h)*v0 + theta*(k1*A - Gamma1 - KPR*(L1 - LSR0 - LPR0)) + (1 - theta)*F0
            = T0 + rhs_v0*v0 + rhs_dL*(L1 - L0) + rhs_f1*f1 + rhs_f0*f0 + rhs_const
              - (KPR + D0)*q0

    with F0 the force at the start and D0 = (1 - theta)*C(z0)*beta(f0)*z0^3 its damping
    factor; the second form is the first multiplied out, one pass per input. Newton solves
    the equation divided by a2 = M/h + theta^2*h*k1*KSR, so the constants that enter rhs and
    the damping coefficients (and KPR) carry that 1/a2.

    (Slots: the float path reads these ~80 times per spindle step, twice as fast as from a
    NamedTuple.)
    """

    keep: float  # f1 = keep*f0 + from_a0*a0 + from_a1*a1 (instantaneous fibres: f1 = a1)
    from_a0: float
    from_a1: float
    KSR: float
    inv_KSR: float
    A_v0: float
    p0_v0: float
    LR: float  # LSR0 + R
    KPR: float  # / a2
    rhs_v0: float
    rhs_dL: float
    rhs_f0: float
    rhs_f1: float
    rhs_const: float
    c_mid: float  # damping C(z)*beta*z^3 = (c_mid*z + c_half*|z|)*beta*z^2 (times a2)
    c_half: float
    beta0_old: float  # (1 - theta)*beta: the start of the step's damping
    beta_drive_old: float
    cM0: float  # the new damping coefficient theta*C*beta1/a2 = cM + cD*sgn(z),
    cMd: float  # cM = cM0 + cMd*f1, cD = cD0 + cDd*f1
    cD0: float
    cDd: float
    inv_a2: float
    th_h_KSR: float
    blend_exp: float  # exponent of |z| in the frozen factor |v|/|z|^3, (3/a - 3)/3
    freq_p: float
    three_over_a: float


def _if(condition, a, b):
    """``a`` where ``condition`` else ``b``: a Python choice for a bool, np.where for arrays."""
    if isinstance(condition, np.ndarray):
        return np.where(condition, a, b)
    return a if condition else b


def _fibre_step_constants(f: FibreParams, h: float, theta: float,
                          convert=float) -> FibreStepConstants:
    """One fibre's constants for a float ``h``; or, with ``f`` holding (3, 1) columns of
    the three fibres and ``convert`` None, the three fibres' as arrays (for h = 1 it gives
    :class:`_Coefficients` the constants that do not depend on h)."""
    lagged = f.tau_s > 0
    rate = h / _if(lagged, f.tau_s, 1.0)
    den = 1.0 + theta * rate
    KSR, KPR, M = f.KSR_FU_L0, f.KPR_FU_L0, f.M_FU_s2_L0
    k1 = 1.0 + KPR / KSR
    inv_a2 = 1.0 / (M / h + (theta * theta * h) * k1 * KSR)
    c_mid = 0.5 * (f.CL + f.CS) * inv_a2
    c_half = 0.5 * (f.CL - f.CS) * inv_a2
    three_over_a = 3.0 / f.a
    constants = dict(
        keep=_if(lagged, (1.0 - (1.0 - theta) * rate) / den, 0.0),
        from_a0=_if(lagged, (1.0 - theta) * rate / den, 0.0),
        from_a1=_if(lagged, theta * rate / den, 1.0),
        KSR=KSR,
        inv_KSR=1.0 / KSR,
        A_v0=(1.0 - theta) * h * KSR,
        p0_v0=(1.0 - theta) * h,
        LR=f.LSR0_L0 + f.R_L0,
        KPR=KPR * inv_a2,
        rhs_v0=(M / h - theta * (1.0 - theta) * h * k1 * KSR) * inv_a2,
        rhs_dL=theta * (k1 * KSR - KPR) * inv_a2,
        rhs_f0=-(1.0 - theta) * f.Gamma_drive_FU * inv_a2,
        rhs_f1=-theta * f.Gamma_drive_FU * inv_a2,
        rhs_const=KPR * (f.LPR0_L0 - f.R_L0) * inv_a2,
        c_mid=c_mid,
        c_half=c_half,
        beta0_old=(1.0 - theta) * f.beta0_FU_s_L0,
        beta_drive_old=(1.0 - theta) * f.beta_drive_FU_s_L0,
        cM0=theta * c_mid * f.beta0_FU_s_L0,
        cMd=theta * c_mid * f.beta_drive_FU_s_L0,
        cD0=theta * c_half * f.beta0_FU_s_L0,
        cDd=theta * c_half * f.beta_drive_FU_s_L0,
        inv_a2=inv_a2,
        th_h_KSR=theta * h * KSR,
        blend_exp=(three_over_a - 3.0) / 3.0,
        freq_p=f.freq_pps**f.p,
        three_over_a=three_over_a,
    )
    if convert is None:
        return constants
    return FibreStepConstants(**{name: convert(x) for name, x in constants.items()})


class StepConstants:
    """The constants of one implicit step (step h, weight theta): per fibre as floats
    (``fibre``) and, on demand, all three as (3, 1) columns (``fibre_columns``)."""

    per_spindle = False

    def __init__(self, c: FibreColumns, h: float, theta: float):
        # Python floats throughout: a step with a new h (a streaming chain's jittery sample
        # interval) rebuilds these, and numpy's per-call overhead would cost ~0.5 ms.
        self.h, self.theta = h, theta
        self.th_h = theta * h
        self.th_h_max = self.th_h
        self.a_is_03 = c.a_is_03
        fibres = c.fibre_params
        self.fibre = tuple(_fibre_step_constants(f, h, theta) for f in fibres)
        self.lagged = tuple(f.tau_s > 0 for f in fibres)
        self.p = tuple(float(f.p) for f in fibres)
        # the chain shares bag2's g^p when their p agree (it has the same static drive)
        self.drive_row = (0, 1, 1 if self.p[2] == self.p[1] else 2)
        self._columns: FibreStepConstants | None = None

    @property
    def fibre_columns(self) -> FibreStepConstants:
        """The constants of the three fibres as (3, 1) columns."""
        if self._columns is None:
            self._columns = FibreStepConstants(**{
                field.name: np.array([[getattr(x, field.name)] for x in self.fibre])
                for field in fields(FibreStepConstants)})
        return self._columns


class SpindleStepConstants:
    """The constants of one implicit step whose size h differs from spindle to spindle (an
    (n,) array; weight theta): :class:`StepConstants`' attributes with the per-fibre
    constants that depend on h as (3, n) arrays (the others (3, 1) columns) in
    ``fibre_columns``, their rows in ``fibre``, and ``th_h`` = theta*h flat over (3*n,) like
    the Newton loop's arrays (fibre rows of n). :meth:`block` gives a block's share."""

    per_spindle = True

    def __init__(self, c: FibreColumns, h: np.ndarray, theta: float, *, _share=None):
        self.theta = theta
        self.a_is_03 = c.a_is_03 if c is not None else _share[0].a_is_03
        if _share is not None:  # a block's share of another's: (k, cols)
            k, cols = _share
            self.h = k.h[cols]
            self.fibre_columns = FibreStepConstants(**{
                name: x if x.shape[1] == 1 else x[:, cols]
                for name, x in _values(k.fibre_columns).items()})
            self.lagged, self.p, self.drive_row = k.lagged, k.p, k.drive_row
        else:
            self.h = h
            fibres = c.fibre_params
            self.lagged = tuple(f.tau_s > 0 for f in fibres)
            self.p = tuple(float(f.p) for f in fibres)
            self.drive_row = (0, 1, 1 if self.p[2] == self.p[1] else 2)
            self.fibre_columns = _per_spindle_constants(_coefficients(c, theta), h)
        th_h = theta * self.h
        self.th_h = np.concatenate((th_h, th_h, th_h))
        self.th_h_max = float(th_h.max())
        self._fibre: tuple[FibreStepConstants, ...] | None = None
        self._blocks: dict[tuple[int, int], SpindleStepConstants] = {}

    @property
    def fibre(self) -> tuple[FibreStepConstants, ...]:
        """Each fibre's constants, rows of (n,) (made on first use: the vectorised step reads
        them only in blocks wider than ROW_BY_ROW_SPINDLES)."""
        if self._fibre is None:
            values = _values(self.fibre_columns)
            self._fibre = tuple(FibreStepConstants(**{name: x[i] for name, x in values.items()})
                                for i in range(3))
        return self._fibre

    def block(self, cols: slice) -> SpindleStepConstants:
        """The constants of the spindles ``cols`` (kept: a chain steps the same sizes over
        its sub-steps)."""
        if cols.start == 0 and cols.stop == self.h.shape[0]:
            return self
        key = (cols.start, cols.stop)
        hit = self._blocks.get(key)
        if hit is None:
            hit = self._blocks[key] = SpindleStepConstants(None, None, self.theta,
                                                           _share=(self, cols))
        return hit


_INV_A2_MULTIPLES = ("KPR", "rhs_dL", "rhs_f0", "rhs_f1", "rhs_const", "c_mid", "c_half",
                     "cM0", "cMd", "cD0", "cDd", "inv_a2")
"""The constants that are an h-independent coefficient times 1/a2(h)."""


class _Coefficients:
    """What the constants of a step with a size per spindle need besides h, for one
    parameter set and theta: (3, 1) columns, and the coefficients of 1/a2 stacked (m, 3, 1)
    so that one multiplication makes all of those constants."""

    def __init__(self, c: FibreColumns, theta: float):
        P = c.fibre_parameter_columns
        # the float path at h = 1 gives every constant that does not depend on h
        at_one = _fibre_step_constants(P, np.ones((1, 1)), theta, convert=None)
        self.theta = theta
        self.fixed = {name: np.broadcast_to(np.asarray(at_one[name], dtype=float), (3, 1))
                      for name in ("KSR", "inv_KSR", "LR", "beta0_old", "beta_drive_old",
                                   "blend_exp", "freq_p", "three_over_a")}
        k1_KSR = (1.0 + P.KPR_FU_L0 / P.KSR_FU_L0) * P.KSR_FU_L0
        c_mid, c_half = 0.5 * (P.CL + P.CS), 0.5 * (P.CL - P.CS)
        coefficient = {
            "KPR": P.KPR_FU_L0, "rhs_dL": theta * (k1_KSR - P.KPR_FU_L0),
            "rhs_f0": -(1.0 - theta) * P.Gamma_drive_FU, "rhs_f1": -theta * P.Gamma_drive_FU,
            "rhs_const": P.KPR_FU_L0 * (P.LPR0_L0 - P.R_L0), "c_mid": c_mid,
            "c_half": c_half, "cM0": theta * c_mid * P.beta0_FU_s_L0,
            "cMd": theta * c_mid * P.beta_drive_FU_s_L0,
            "cD0": theta * c_half * P.beta0_FU_s_L0,
            "cDd": theta * c_half * P.beta_drive_FU_s_L0, "inv_a2": np.ones((3, 1))}
        self.of_inv_a2 = np.stack([np.broadcast_to(coefficient[name], (3, 1))
                                   for name in _INV_A2_MULTIPLES])
        self.M, self.k1_KSR, self.KSR = P.M_FU_s2_L0, k1_KSR, P.KSR_FU_L0
        self.lagged = (P.tau_s > 0).astype(float)
        self.tau_safe = np.where(P.tau_s > 0, P.tau_s, 1.0)


def _coefficients(c: FibreColumns, theta: float) -> _Coefficients:
    """The :class:`_Coefficients` of ``c`` for ``theta`` (kept on ``c``)."""
    theta = float(theta)
    hit = c.per_spindle_coefficients
    if hit is None or hit.theta != theta:
        hit = c.per_spindle_coefficients = _Coefficients(c, theta)
    return hit


def _per_spindle_constants(k: _Coefficients, h: np.ndarray) -> FibreStepConstants:
    """:func:`_fibre_step_constants` of the three fibres for a step size per spindle, as
    (3, n) arrays (those independent of h as (3, 1) columns), in ~30 array operations: the
    constants that are multiples of 1/a2 in one multiplication of their stacked
    coefficients. Equal to the float path to rounding (``tests/test_spindle_core.py``);
    a second form of the same constants because it pays: 295 -> 50 us per build at
    n = 128 spindles, 714 -> 100 at 864 (timeit, 2026-12-01), once per encoder sample."""
    theta = k.theta
    row = h[None, :]
    M_over_h = k.M / row
    inv_a2 = 1.0 / (M_over_h + (theta * theta * row) * k.k1_KSR)
    multiples = k.of_inv_a2 * inv_a2[None]
    out = dict(zip(_INV_A2_MULTIPLES, multiples, strict=True))
    out["rhs_v0"] = (M_over_h - (theta * (1.0 - theta) * row) * k.k1_KSR) * inv_a2
    rate = row / k.tau_safe
    den = 1.0 + theta * rate
    out["keep"] = (1.0 - (1.0 - theta) * rate) / den * k.lagged
    out["from_a0"] = (1.0 - theta) * rate / den * k.lagged
    from_a1 = theta * rate / den
    out["from_a1"] = np.where(k.lagged > 0, from_a1, 1.0)
    old_h = (1.0 - theta) * row
    out["A_v0"] = old_h * k.KSR
    out["p0_v0"] = np.broadcast_to(old_h, inv_a2.shape)
    out["th_h_KSR"] = (theta * row) * k.KSR
    out.update(k.fixed)
    return FibreStepConstants(**out)


def _values(constants: FibreStepConstants) -> dict:
    return {f.name: getattr(constants, f.name) for f in fields(FibreStepConstants)}


class _ParameterColumns:
    """The fibre parameters as (3, 1) columns under :class:`FibreParams`' names."""

    def __init__(self, params: SpindleParams):
        for f in fields(FibreParams):
            value = getattr(params.fibres[0], f.name)
            if isinstance(value, int | float):
                setattr(self, f.name, params.column(f.name))


def spindle_step_constants(c: FibreColumns, h: np.ndarray, theta: float) -> SpindleStepConstants:
    """The :class:`SpindleStepConstants` of ``c`` for the step sizes ``h`` (n,) and
    ``theta``, kept until either changes."""
    # keyed on float64 values: numpy compares a float32 array with float64 ones as float64,
    # but a cached float32 h would make every later step float32
    h = np.asarray(h, dtype=np.float64)
    theta = float(theta)
    hit = c.spindle_step_constants
    if (hit is None or hit.theta != theta or hit.h.shape != h.shape
            or not np.array_equal(hit.h, h)):
        hit = c.spindle_step_constants = SpindleStepConstants(c, np.array(h, dtype=float),
                                                              theta)
    return hit


def step_constants(c: FibreColumns, h: float, theta: float) -> StepConstants:
    """The :class:`StepConstants` of ``c`` for (h, theta), kept until either changes.

    The key is the Python floats h and theta stand for: numpy compares ``np.float32(0.001)``
    equal to ``0.001`` (the Python float is cast down), so a key kept as a float32 would
    hand its float32 constants to every later float64 step of that size."""
    h, theta = float(h), float(theta)
    hit = c.step_constants
    if hit is None or hit.h != h or hit.theta != theta:
        hit = c.step_constants = StepConstants(c, h, theta)
    return hit


def check_finite(T1: np.ndarray, v1: np.ndarray, h: float) -> None:
    """Raise ``FloatingPointError`` if the step's new tension or velocity is not finite."""
    # A sum is finite only if every term is (the values are far below overflow).
    if not math.isfinite(float(T1.sum()) + float(v1.sum())):
        raise FloatingPointError(
            "the spindle step produced a non-finite tension or velocity; state left unchanged "
            f"(step {h!r} s)"
        )
