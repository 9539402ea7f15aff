"""The Mileusnic (2006) spindle as a state that a theta-method steps in place.

Each intrafusal fibre (bag1, bag2, chain) carries its sensory-region tension ``T`` (FU), its
polar-region velocity ``v`` (L0/s) and its fusimotor activation ``f``. In the variables (T, v)
the model reads

    dT/dt   = KSR * (dL - v)
    M dv/dt = T - Gamma - KPR*(L - LSR0 - T/KSR - LPR0) - C*beta*sgn(v)|v|^a*(L - LSR0 - T/KSR - R)

which is the published second-order form (state T, dT/dt) with v = dL - (dT/dt)/KSR
substituted: the M * d2L/dt2 input term cancels exactly, so ramp corners need no impulse and
the input enters only through dT/dt = KSR*(dL - v). The integrator takes the dL part exactly:
over a step it contributes KSR*(L1 - L0), so it needs the sampled lengths and no derivative of
them (a sampled velocity would add an O(h) error at every ramp corner). ``C`` is CL when the
polar region lengthens (v > 0) and CS otherwise; the choice follows the sign of v, the
spec's formulation (not the sign of dL).

The damping's length factor, the polar length beyond R, is clipped at 0: R is the length
below which the polar region produces no force (Mileusnic 2006, Table 1), so a polar region
shorter than R is undamped rather than pushed (the published product turns into a negative
damping there). That happens only near the short end of the length range, e.g. at rest at
0.5 L0 with static drive >= ~100 pps, where the unclipped step equation had spurious roots
and a guess of 0/0 (the first step failed); everywhere else the model is the published one.

The implicit settings solve, per fibre and step, one scalar equation that is monotone in the
new v. It is solved for z = sgn(v)|v|^(a/3) instead of v: the damping sgn(v)|v|^a is z^3 and
v is z^10 (a = 0.3), so Newton's method meets no infinite slope (as it would at v = 0) and
evaluates no fractional power. The state keeps z beside v.

Shapes: public state arrays have a leading spindle axis, ``(n, 3)`` with columns
(bag1, bag2, chain). They are transposed views of fibre-major ``(3, n)`` buffers, the layout
the arithmetic runs on.

Speed (every path solves the same equation to the same tolerance, so they agree to
rounding, ~1e-13 pps):

- up to SMALL_N spindles the implicit step runs on Python floats, fibre by fibre (numpy's
  per-call overhead would dominate);
- beyond, it runs in blocks of CHUNK_SPINDLES spindles whose working arrays stay in cache,
  in place in buffers that each state keeps (its ``_workspace``, created on first use) and
  reuses from step to step. Each block iterates Newton until its own fibres have converged
  and hands the last few slow ones to a tail that finishes them together;
- the starting guess solves the step equation with |v|/|z|^3 frozen and blends it toward the
  previous z by the first-order correction for that freeze (see ``_Workspace._setup``),
  which leaves most fibres two or three Newton iterations from convergence. Once a state
  has taken three steps of one size, the numpy path guesses instead by extrapolating its last
  three z (see ``_Workspace``): as close, and some 20 passes over each block cheaper.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spindle.methods import Method, get_method
from spindle.params import CAT, FibreParams, SpindleParams

LENGTH_RANGE_L0 = (0.5, 1.5)
"""Accepted normalised fascicle lengths. Below ~0.5 L0 the polar region becomes shorter than
the damping's reference length R even without drive (the damping is clipped there, see the
module docstring, and the model stops describing a spindle); above 1.5 L0 the model was never
fitted."""

MAX_SPEED_L0_S = 10.0
"""Largest accepted |dL/dt|: about the maximum shortening velocity of fast muscle fibres."""

NEWTON_MAX_ITER = 60
NEWTON_FULL_ITER = 3
NEWTON_TOL_Z = 1e-9
NEWTON_MAX_DZ = 0.25


@dataclass
class SpindleState:
    """Mutable state of ``n`` spindles (arrays with a leading spindle axis).

    Attributes:
        tension_FU: (n, 3) sensory-region tension of bag1, bag2, chain.
        polar_velocity_L0_s: (n, 3) polar-region velocity v.
        velocity_root: (n, 3) z = sgn(v)|v|^(a/3), kept beside v (see module docstring).
        activation: (n, 3) fusimotor activation f in [0, 1].
        length_L0: (n,) the fascicle length at the state's time.
        gamma_dyn_pps, gamma_stat_pps: (n,) the fusimotor drive at the state's time.
    """

    tension_FU: np.ndarray
    polar_velocity_L0_s: np.ndarray
    velocity_root: np.ndarray
    activation: np.ndarray
    length_L0: np.ndarray
    gamma_dyn_pps: np.ndarray
    gamma_stat_pps: np.ndarray

    @property
    def n(self) -> int:
        return self.length_L0.shape[0]

    def copy(self) -> SpindleState:
        return SpindleState(
            *(_fibre_major(a.T.copy()) if a.ndim == 2 else a.copy() for a in self._arrays())
        )

    def __getstate__(self) -> dict:
        # the step's scratch buffers (see advance) are not part of the state
        return {k: v for k, v in self.__dict__.items() if k != "_workspace"}

    def _arrays(self) -> tuple[np.ndarray, ...]:
        return (
            self.tension_FU, self.polar_velocity_L0_s, self.velocity_root, self.activation,
            self.length_L0, self.gamma_dyn_pps, self.gamma_stat_pps,
        )


def _fibre_major(buffer_3n: np.ndarray) -> np.ndarray:
    """A (n, 3) view of a C-contiguous (3, n) buffer."""
    return np.ascontiguousarray(buffer_3n).T


def _as_spindle_vector(name: str, value: object, n: int | None = None) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.ndim > 1:
        raise ValueError(f"{name} must be a scalar or a 1-D array over spindles, got shape "
                         f"{arr.shape}")
    if n is not None:
        try:
            arr = np.broadcast_to(arr, (n,))
        except ValueError:
            raise ValueError(
                f"{name} has shape {arr.shape}, which does not broadcast to the {n} spindles"
            ) from None
    return np.array(arr, dtype=float, ndmin=1)


def check_inputs(
    length_L0: np.ndarray, gamma_dyn_pps: np.ndarray, gamma_stat_pps: np.ndarray
) -> None:
    """Raise ``ValueError`` naming the offending value and limit for inputs out of range."""
    for name, arr in (
        ("length_L0", length_L0), ("gamma_dyn_pps", gamma_dyn_pps),
        ("gamma_stat_pps", gamma_stat_pps),
    ):
        finite = np.isfinite(arr)
        if not finite.all():
            bad = float(arr[~finite].flat[0])
            raise ValueError(f"{name} contains {bad!r}; every value must be finite")
    lo, hi = LENGTH_RANGE_L0
    if length_L0.size and (length_L0.min() < lo or length_L0.max() > hi):
        bad = float(length_L0.min() if length_L0.min() < lo else length_L0.max())
        raise ValueError(f"length_L0={bad!r} is outside the model's range [{lo}, {hi}] L0")
    for name, arr in (("gamma_dyn_pps", gamma_dyn_pps), ("gamma_stat_pps", gamma_stat_pps)):
        if arr.size and arr.min() < 0:
            raise ValueError(
                f"{name}={float(arr.min())!r} is negative; fusimotor rates must be >= 0"
            )


def check_speed(length_change_L0: np.ndarray, dt_s: float) -> None:
    """Refuse a length change faster than :data:`MAX_SPEED_L0_S` over ``dt_s``."""
    if length_change_L0.size:
        fastest = np.abs(length_change_L0).max() / dt_s
        if fastest > MAX_SPEED_L0_S:
            raise ValueError(
                f"length changes at {fastest!r} L0/s, above the limit |dL/dt| <= "
                f"{MAX_SPEED_L0_S} L0/s"
            )


def check_step(step_s: float, method: Method) -> None:
    """Refuse a non-positive step or one beyond the method's limit."""
    if not (np.isfinite(step_s) and step_s > 0):
        raise ValueError(f"step={step_s!r} s must be finite and > 0")
    if step_s > method.max_step_s * (1 + 1e-9):
        raise ValueError(
            f"step={step_s!r} s exceeds the {method.name} limit of {method.max_step_s!r} s"
        )


MAX_DRIVE_POWER = float(np.finfo(float).max)
"""g^p is capped here: a drive so large that g^p overflows (g > 1.3e154 pps for p = 2) has
activation exactly 1 (g^p / (g^p + freq^p) rounds to 1 long before), as in the C port,
instead of inf/inf = NaN."""


def activation_target(drive_pps: np.ndarray, freq_pps: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Steady-state fusimotor activation g^p / (g^p + freq^p) (dimensionless), saturating at
    1 for any finite drive (see :data:`MAX_DRIVE_POWER`)."""
    with np.errstate(over="ignore"):
        if np.all(p == 2.0):
            gp = np.minimum(drive_pps * drive_pps, MAX_DRIVE_POWER)
            return gp / (gp + freq_pps * freq_pps)
        gp = np.minimum(drive_pps**p, MAX_DRIVE_POWER)
    return gp / (gp + freq_pps**p)


def _drive_rows(gamma_dyn_pps: np.ndarray, gamma_stat_pps: np.ndarray) -> np.ndarray:
    """Fusimotor drive of (bag1, bag2, chain): dynamic, static, static; shape (3, n)."""
    return np.stack((gamma_dyn_pps, gamma_stat_pps, gamma_stat_pps))


class _Columns:
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
        self.LNSR = col("LNSR_L0")
        self.LNPR = col("LNPR_L0")
        self.X = col("X")
        self.Lsec = col("Lsec_L0")
        self.G_pri = col("G_primary_pps_L0")
        self.G_sec = col("G_secondary_pps_L0")
        self.freq = col("freq_pps")
        self.p = col("p")
        self.tau = col("tau_s")
        self.lagged = self.tau[:, 0] > 0
        self.tau_safe = np.where(self.tau > 0, self.tau, 1.0)
        self.k1 = 1.0 + self.KPR / self.KSR
        self.S = params.S
        # With a = 0.3, v = z^10 * sgn(z): a polynomial, many times cheaper than a power.
        self.a_is_03 = bool(np.all(self.a == 0.3))
        self.three_over_a = 3.0 / self.a
        self.step_constants: _StepConstants | None = None
        self.fibre_params = params.fibres
        self.S_float = float(params.S)
        # The afferent potentials multiplied out, as Python floats: primary of fibre i
        # G*(T/KSR - (LNSR - LSR0)) = T*g - n with (g, n) = primary_lin[i]; secondary of
        # bag2 and chain G2*(X*Lsec/LSR0*(T/KSR - (LNSR - LSR0)) + (1 - X)*Lsec/LPR0*
        # (L - T/KSR - LSR0 - LNPR)) = T*a + L*b + c with (a, b, c) = secondary_lin[i - 1].
        self.primary_lin = tuple(
            (f.G_primary_pps_L0 / f.KSR_FU_L0, f.G_primary_pps_L0 * (f.LNSR_L0 - f.LSR0_L0))
            for f in params.fibres
        )
        self.secondary_lin = tuple(
            (f.G_secondary_pps_L0 * (f.X * f.Lsec_L0 / f.LSR0_L0
                                     - (1.0 - f.X) * f.Lsec_L0 / f.LPR0_L0) / f.KSR_FU_L0,
             f.G_secondary_pps_L0 * (1.0 - f.X) * f.Lsec_L0 / f.LPR0_L0,
             -f.G_secondary_pps_L0 * (f.X * f.Lsec_L0 / f.LSR0_L0 * (f.LNSR_L0 - f.LSR0_L0)
                                      + (1.0 - f.X) * f.Lsec_L0 / f.LPR0_L0
                                      * (f.LSR0_L0 + f.LNPR_L0)))
            for f in params.fibres[1:]
        )


_COLUMNS_CACHE: dict[int, tuple[SpindleParams, _Columns]] = {}


def columns(params: SpindleParams) -> _Columns:
    key = id(params)
    hit = _COLUMNS_CACHE.get(key)
    if hit is None or hit[0] is not params:
        hit = (params, _Columns(params))
        if len(_COLUMNS_CACHE) > 64:
            _COLUMNS_CACHE.clear()
        _COLUMNS_CACHE[key] = hit
    return hit[1]


def _z_from_velocity(v: np.ndarray, c: _Columns) -> np.ndarray:
    return np.sign(v) * np.abs(v) ** (c.a / 3.0)


def _force(T, z, L, beta, Gamma, c):
    """M dv/dt of each fibre (FU); the damping C*beta*sgn(v)|v|^a is C*beta*z^3, times the
    polar length beyond R clipped at 0 (see the module docstring)."""
    polar = L - c.LSR0 - T / c.KSR
    damping = np.where(z > 0, c.CL, c.CS) * beta * (z * z * z)
    return T - Gamma - c.KPR * (polar - c.LPR0) - damping * np.maximum(polar - c.R, 0.0)


def equilibrium_state(
    length_L0: float | np.ndarray,
    gamma_dyn_pps: float | np.ndarray = 0.0,
    gamma_stat_pps: float | np.ndarray = 0.0,
    params: SpindleParams = CAT,
) -> SpindleState:
    """Spindles at rest at the given length and drive: v = 0 and every activation at target.

    With v = 0 the fibre force balance gives T in closed form,
    T = (Gamma + KPR*(L - LSR0 - LPR0)) / (1 + KPR/KSR). The number of spindles n is the
    broadcast size of the inputs (scalars or 1-D arrays).
    """
    arrays = [np.asarray(x, dtype=float) for x in (length_L0, gamma_dyn_pps, gamma_stat_pps)]
    try:
        if any(a.ndim > 1 for a in arrays):
            raise ValueError
        n = int(np.broadcast_shapes(*(a.shape for a in arrays), (1,))[0])
    except ValueError:
        raise ValueError(
            "length_L0, gamma_dyn_pps and gamma_stat_pps must be scalars or 1-D arrays of one "
            f"common length, got shapes {[a.shape for a in arrays]}"
        ) from None
    L, gd, gs = (_as_spindle_vector(name, a, n) for name, a in zip(
        ("length_L0", "gamma_dyn_pps", "gamma_stat_pps"), arrays, strict=True))
    check_inputs(L, gd, gs)
    c = columns(params)
    f = activation_target(_drive_rows(gd, gs), c.freq, c.p)
    T = (c.Gamma_drive * f + c.KPR * (L - c.LSR0 - c.LPR0)) / c.k1
    zeros = np.zeros((3, n))
    return SpindleState(
        tension_FU=_fibre_major(T), polar_velocity_L0_s=_fibre_major(zeros),
        velocity_root=_fibre_major(zeros.copy()), activation=_fibre_major(f),
        length_L0=L, gamma_dyn_pps=gd, gamma_stat_pps=gs,
    )


def afferents(state: SpindleState, params: SpindleParams = CAT) -> tuple[np.ndarray, np.ndarray]:
    """Ia and II rates (pps) of each spindle in ``state``; each of shape (n,)."""
    return _afferents(state.tension_FU.T, state.length_L0, columns(params))


AFFERENT_CHUNK = 8192
"""Spindles per block of :func:`_afferents` (its temporaries stay in cache)."""


def _afferents(T: np.ndarray, L: np.ndarray, c: _Columns) -> tuple[np.ndarray, np.ndarray]:
    """Ia and II (pps), each (n,), of fibre tensions T (3, n) at fascicle lengths L (n,).

    Every fibre's potential is clipped at 0 before they are combined (a slack fibre neither
    excites nor inhibits the shared ending); the totals are then >= 0 by construction. Each
    potential is linear in the fibre's T (and the secondary's in L too); it is evaluated in
    that multiplied-out form (:attr:`_Columns.primary_lin`, :attr:`_Columns.secondary_lin`),
    fibre row by fibre row.
    """
    n = T.shape[1]
    if n <= SMALL_N:
        return _afferents_small(T, L, c)
    mul, add, sub, top = np.multiply, np.add, np.subtract, np.maximum
    L = np.broadcast_to(L, (n,))
    ia, ii = np.empty(n), np.empty(n)
    m = min(n, AFFERENT_CHUNK)
    buffers = np.empty((3, m))
    (g0, n0), (g1, n1), (g2, n2) = c.primary_lin
    (a1, b1, c1), (a2, b2, c2) = c.secondary_lin
    for j0 in range(0, n, m):
        cols = slice(j0, min(n, j0 + m))
        x, y, t = buffers[:, : cols.stop - j0]
        T0, T1, T2, Lc = T[0, cols], T[1, cols], T[2, cols], L[cols]
        mul(T0, g0, out=x)
        sub(x, n0, out=x)
        top(x, 0.0, out=x)
        mul(T1, g1, out=y)
        sub(y, n1, out=y)
        top(y, 0.0, out=y)
        mul(T2, g2, out=t)
        sub(t, n2, out=t)
        top(t, 0.0, out=t)
        add(y, t, out=y)
        out = ia[cols]
        top(x, y, out=out)
        np.minimum(x, y, out=t)
        mul(t, c.S_float, out=t)
        add(out, t, out=out)
        mul(T1, a1, out=x)
        mul(Lc, b1, out=t)
        add(x, t, out=x)
        add(x, c1, out=x)
        top(x, 0.0, out=x)
        mul(T2, a2, out=y)
        mul(Lc, b2, out=t)
        add(y, t, out=y)
        add(y, c2, out=y)
        top(y, 0.0, out=y)
        add(x, y, out=ii[cols])
    return ia, ii


def step(
    state: SpindleState,
    length_L0: float | np.ndarray,
    gamma_dyn_pps: float | np.ndarray,
    gamma_stat_pps: float | np.ndarray,
    dt_s: float,
    params: SpindleParams = CAT,
    method: str | Method | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Advance ``state`` by one step of ``dt_s`` in place; return (Ia, II) in pps, shape (n,).

    The inputs are the fascicle length and fusimotor drive at the end of the step (the state
    holds those at its start). Bad inputs raise ``ValueError`` and leave ``state`` unchanged.
    """
    m = get_method(method)
    check_step(dt_s, m)
    n = state.n
    L, gd, gs = (
        _as_spindle_vector(name, x, n)
        for name, x in (("length_L0", length_L0), ("gamma_dyn_pps", gamma_dyn_pps),
                        ("gamma_stat_pps", gamma_stat_pps))
    )
    check_inputs(L, gd, gs)
    check_speed(L - state.length_L0, dt_s)
    c = columns(params)
    new = advance(state, L, gd, gs, dt_s, m.theta, c)
    commit(state, new, L, gd, gs)
    return _afferents(new[0], L, c)


def commit(state: SpindleState, new, L, gd, gs) -> None:
    """Write the result of :func:`advance` into ``state``."""
    T, v, u, f = new
    state.tension_FU.T[...] = T
    state.polar_velocity_L0_s.T[...] = v
    state.velocity_root.T[...] = u
    state.activation.T[...] = f
    state.length_L0[...] = L
    state.gamma_dyn_pps[...] = gd
    state.gamma_stat_pps[...] = gs


def advance(state, L1, gd1, gs1, h, theta, c):
    """One theta-method step from the state to (L1, gd1, gs1), unchecked.

    Returns (T1, v1, u1, f1), each (3, n). Nothing in ``state`` is modified: the caller
    commits the result once it is known to be finite, so a failed step leaves the state as it
    was. For the implicit settings the returned arrays are buffers that the state's workspace
    reuses: they are valid until the next ``advance`` of the same state (``commit`` copies
    them into the state, ``_afferents`` reads them).
    """
    if theta == 0.0:
        return _advance_explicit(state, L1, gd1, gs1, h, c)
    if state.n <= SMALL_N:
        return _advance_small(state, L1, gd1, gs1, h, theta, c)
    # a fibre at rest with its polar region no longer than R has no frozen-factor slope: its
    # guess divides by 0 and is then replaced (_bound_guess); non-finite results are caught
    # by the finite check at the end of the step
    with np.errstate(divide="ignore", invalid="ignore"):
        return _workspace(state, _step_constants(c, h, theta)).advance(state, L1, gd1, gs1)


def _advance_explicit(state, L1, gd1, gs1, h, c):
    """Forward Euler (theta = 0): every term from the state at the start of the step."""
    T0 = state.tension_FU.T
    v0 = state.polar_velocity_L0_s.T
    u0 = state.velocity_root.T
    f0 = state.activation.T
    L0 = state.length_L0
    a1 = activation_target(_drive_rows(gd1, gs1), c.freq, c.p)
    a0 = activation_target(_drive_rows(state.gamma_dyn_pps, state.gamma_stat_pps), c.freq, c.p)
    f1 = f0 + (h / c.tau_safe) * (a0 - f0)
    f1[~c.lagged] = a1[~c.lagged]
    F0 = _force(T0, u0, L0, c.beta0 + c.beta_drive * f0, c.Gamma_drive * f0, c)
    T1 = T0 + c.KSR * (L1 - L0) - (h * c.KSR) * v0
    v1 = v0 + (h / c.M) * F0
    u1 = _z_from_velocity(v1, c)
    _check_finite(T1, v1, h)
    return T1, v1, u1, f1


def _check_finite(T1, v1, h):
    # A sum is finite only if every term is (the values are far below overflow).
    if not math.isfinite(float(T1.sum()) + float(v1.sum())):
        raise FloatingPointError(
            "the spindle step produced a non-finite tension or velocity; state left unchanged "
            f"(step {h!r} s)"
        )


class _StepConstants:
    """Per-fibre constants of one implicit step (step h, weight theta): a tuple of Python
    floats per fibre (``fibre``, in the order of ``NAMES``) and, on demand, the same as
    (3, 1) columns (``fibre_columns``).

    The theta-method's equation for the new z (see :func:`_newton_loop`) needs, from the
    start of the step, with q0 = L0 - LSR0 - R - T0/KSR (the polar length minus R):

        A   = T0 + KSR*(L1 - L0) - (1 - theta)*h*KSR*v0          (T1 = A - theta*h*KSR*v1)
        p0  = q0 + (1 - theta)*h*v0                               (= L1 - LSR0 - R - A/KSR)
        rhs = (M/h)*v0 + theta*(k1*A - Gamma1 - KPR*(L1 - LSR0 - LPR0)) + (1 - theta)*F0
            = T0 + rhs_v0*v0 + rhs_dL*(L1 - L0) + rhs_f1*f1 + rhs_f0*f0 + rhs_const
              - (KPR + D0)*q0

    with F0 the force at the start and D0 = (1 - theta)*C(z0)*beta(f0)*z0^3 its damping
    factor; the second form is the first multiplied out, one pass per input. The Newton loop
    solves the equation divided by a2 = M/h + theta^2*h*k1*KSR, so the constants that enter
    rhs and the damping coefficients here (and KPR) carry that 1/a2.
    """

    NAMES = ("keep", "from_a0", "from_a1", "KSR", "inv_KSR", "A_v0", "p0_v0", "LR", "KPR",
             "rhs_v0", "rhs_dL", "rhs_f0", "rhs_f1", "rhs_const", "c_mid", "c_half",
             "beta0_old", "beta_drive_old", "cM0", "cMd", "cD0", "cDd", "inv_a2", "th_h_KSR",
             "blend_exp", "freq_p", "three_over_a")
    """The per-fibre constants, in the order of each tuple in ``fibre``."""

    def __init__(self, c: _Columns, h: float, theta: float):
        # Python floats throughout: a step with a new h (a streaming chain's jittery sample
        # interval) rebuilds these, and numpy's per-call overhead would cost ~0.5 ms.
        self.h, self.theta = h, theta
        self.th_h = theta * h
        self.a_is_03 = c.a_is_03
        fibres = c.fibre_params
        self.fibre = tuple(self._fibre_constants(f, h, theta) for f in fibres)
        self.lagged = tuple(f.tau_s > 0 for f in fibres)
        self.p = tuple(float(f.p) for f in fibres)
        # the chain shares bag2's g^p when their p agree (it has the same static drive)
        self.drive_row = (0, 1, 1 if self.p[2] == self.p[1] else 2)
        self.th_h_KSR_floats = tuple(x[self.NAMES.index("th_h_KSR")] for x in self.fibre)
        self.three_over_a_floats = tuple(x[self.NAMES.index("three_over_a")]
                                         for x in self.fibre)
        self._columns: tuple[np.ndarray, ...] | None = None

    @staticmethod
    def _fibre_constants(f: FibreParams, h: float, theta: float) -> tuple[float, ...]:
        lagged = f.tau_s > 0
        rate = h / (f.tau_s if lagged else 1.0)
        den = 1.0 + theta * rate
        KSR, KPR, M = f.KSR_FU_L0, f.KPR_FU_L0, f.M_FU_s2_L0
        k1 = 1.0 + KPR / KSR
        # The equation for z is solved divided by its |v| coefficient a2 (see
        # _newton_loop): rhs, the damping coefficients and KPR carry the 1/a2.
        a2 = M / h + (theta * theta * h) * k1 * KSR
        inv_a2 = 1.0 / a2
        # Damping C(z)*beta*z^3 = (Cmid*z + Chalf*|z|)*beta*z^2, C = CL for z > 0, CS else.
        c_mid = 0.5 * (f.CL + f.CS) * inv_a2
        c_half = 0.5 * (f.CL - f.CS) * inv_a2
        three_over_a = 3.0 / f.a
        constants = {
            # f1 = keep*f0 + from_a0*a0 + from_a1*a1; instantaneous fibres take f1 = a1.
            "keep": (1.0 - (1.0 - theta) * rate) / den if lagged else 0.0,
            "from_a0": (1.0 - theta) * rate / den if lagged else 0.0,
            "from_a1": theta * rate / den if lagged else 1.0,
            "KSR": KSR,
            "inv_KSR": 1.0 / KSR,
            "A_v0": (1.0 - theta) * h * KSR,
            "p0_v0": (1.0 - theta) * h,
            "LR": f.LSR0_L0 + f.R_L0,
            "KPR": KPR * inv_a2,
            "rhs_v0": (M / h - theta * (1.0 - theta) * h * k1 * KSR) * inv_a2,
            "rhs_dL": theta * (k1 * KSR - KPR) * inv_a2,
            "rhs_f0": -(1.0 - theta) * f.Gamma_drive_FU * inv_a2,
            "rhs_f1": -theta * f.Gamma_drive_FU * inv_a2,
            "rhs_const": KPR * (f.LPR0_L0 - f.R_L0) * inv_a2,
            "c_mid": c_mid,
            "c_half": c_half,
            "beta0_old": (1.0 - theta) * f.beta0_FU_s_L0,
            "beta_drive_old": (1.0 - theta) * f.beta_drive_FU_s_L0,
            # The new step's damping coefficients theta*C*beta1/a2, as cM +- cD.
            "cM0": theta * c_mid * f.beta0_FU_s_L0,
            "cMd": theta * c_mid * f.beta_drive_FU_s_L0,
            "cD0": theta * c_half * f.beta0_FU_s_L0,
            "cDd": theta * c_half * f.beta_drive_FU_s_L0,
            "inv_a2": inv_a2,
            "th_h_KSR": theta * h * KSR,
            "blend_exp": (three_over_a - 3.0) / 3.0,
            "freq_p": f.freq_pps**f.p,
            "three_over_a": three_over_a,
        }
        return tuple(float(constants[name]) for name in _StepConstants.NAMES)

    @property
    def fibre_columns(self) -> tuple[np.ndarray, ...]:
        """The constants as (3, 1) columns, in the order of ``NAMES``."""
        if self._columns is None:
            self._columns = tuple(np.array([[x[j]] for x in self.fibre])
                                  for j in range(len(self.NAMES)))
        return self._columns


def _step_constants(c: _Columns, h: float, theta: float) -> _StepConstants:
    hit = c.step_constants
    if hit is None or hit.h != h or hit.theta != theta:
        hit = c.step_constants = _StepConstants(c, h, theta)
    return hit


CHUNK_SPINDLES = 6144
"""Spindles per block of the vectorised step: every working array of a block stays in the
core's cache (the step makes ~150 passes over them), and each block leaves the Newton loop
as soon as all of its own fibres have converged."""

ROW_BY_ROW_SPINDLES = 2048
"""From this block width on, the start-of-step terms go fibre row by fibre row."""

TAIL_FRACTION = 8
"""A block hands its still-unconverged fibres to a common tail once at most 1/TAIL_FRACTION
of them remain (a few sign changes of v need more iterations than the rest)."""


EXTRAPOLATE_SPINDLES = 8192
"""From this many spindles on, the guess extrapolates the last steps' z (see
:class:`_Workspace`). The few fibres it leaves far off (mostly where v is about to cross 0)
go to the common tail, whose per-call cost outweighs the saving below this size."""

EXTRAPOLATE_MAX_ITER = 3.5
"""Mean Newton iterations per block above which a step's extrapolated guess counts as worse
than the frozen-factor one (which needs about 3): inputs noisy from sample to sample (length
noise of ~1e-4 L0 at 1 ms) make the extrapolation ring."""

EXTRAPOLATE_COOLDOWN = 64
"""Steps on the frozen-factor guess after such a step, before extrapolating again."""

HISTORY_PROBE = 61
"""Every this many spindles, the state's z is compared with the last step's output before
that step's history steers the next guess (see :class:`_Workspace`)."""


class _Block:
    """Scratch arrays for a block of ``w`` spindles: flat (3*w,) buffers and (3, w) views."""

    NAMES = ("a1", "cM", "cD", "A", "p0", "rhs", "z", "az", "sq", "t9", "w", "cb",
             "q", "g", "dv", "dg", "dz", "tmp", "p3")

    def __init__(self, w: int):
        self.w = w
        self.flat = {name: np.empty(3 * w) for name in self.NAMES}
        self.rows = {name: a.reshape(3, w) for name, a in self.flat.items()}
        self.dL = np.empty(w)
        self.moving = np.empty(3 * w, dtype=bool)
        self.same_sign = self.moving.reshape(3, w)
        self.gp1 = np.empty((3, w))
        self.gp0 = np.empty((3, w))
        self.k: _StepConstants | None = None

    def prepare(self, k: _StepConstants) -> None:
        """Expand the step's per-fibre constants that the Newton loop uses to (3*w,)."""
        if self.k is not k:
            self.th_h_KSR = np.repeat(k.th_h_KSR_floats, self.w)
            self.blend_exp = np.repeat([x[k.NAMES.index("blend_exp")] for x in k.fibre], self.w)
            if not k.a_is_03:
                # per-fibre exponents, expanded like the data (rows of w)
                e = np.array(k.three_over_a_floats)
                self.flat["power"] = np.repeat(e - 1.0, self.w)
                self.flat["three_over_a"] = np.repeat(e, self.w)
                self.flat["w_coef"] = np.repeat((3.0 + e) * k.th_h, self.w)
            self.k = k


class _Workspace:
    """Reused buffers of the vectorised implicit step of one state (n spindles).

    :func:`advance` returns the output arrays ``T1, v1, z1, f1`` themselves; they hold the
    result until the next ``advance`` of the same state.

    The z outputs rotate through four buffers, so the two before the latest stay available: once
    three steps of the same size have run (and n >= EXTRAPOLATE_SPINDLES), the Newton guess is
    the quadratic extrapolation 3*(z0 - z_-1) + z_-2 of the state's z and those two: 3 passes
    over the block instead of the ~20 of the frozen-factor guess of :meth:`_setup`, and about as
    close (median error a few 1e-6 in z on smooth motion), except for a few percent of fibres
    whose v is about to cross 0, which end in the tail and start there again from the
    frozen-factor guess. The history only steers the guess: if the state was changed in between
    (a reset, a failed step, a step that was not committed), Newton still converges to the same
    tolerance, from farther away. A sample of the state's z is checked against the latest output
    (every HISTORY_PROBE-th spindle), so a state reset or edited between steps falls back to the
    frozen-factor guess instead of a far-off one, and a step whose blocks needed more than
    EXTRAPOLATE_MAX_ITER Newton iterations on average (inputs noisy from sample to sample)
    returns to it for EXTRAPOLATE_COOLDOWN steps.
    """

    def __init__(self, n: int):
        self.n = n
        self.T1 = np.empty((3, n))
        self.v1 = np.empty((3, n))
        self.z_ring = [np.empty((3, n)) for _ in range(4)]
        self.z1 = self.z_ring[0]
        self.history = 0  # consecutive steps of the current size whose z the ring holds
        self.cooldown = 0  # steps left before the extrapolated guess is tried again
        self.f1 = np.empty((3, n))
        m = min(n, CHUNK_SPINDLES)
        self.blocks = {m: _Block(m)}
        if n % m:
            self.blocks[n % m] = _Block(n % m)
        self.k: _StepConstants | None = None

    def prepare(self, k: _StepConstants) -> None:
        if k is not self.k:
            self.history = 0  # an extrapolation over a different step size is no guess
        self.k = k
        for b in self.blocks.values():
            b.prepare(k)

    def advance(self, state, L1, gd1, gs1):
        k, n = self.k, self.n
        T0 = state.tension_FU.T
        v0 = state.polar_velocity_L0_s.T
        z0 = state.velocity_root.T
        f0 = state.activation.T
        L0 = state.length_L0
        gd0, gs0 = state.gamma_dyn_pps, state.gamma_stat_pps
        L1 = np.broadcast_to(L1, (n,))
        gd1 = np.broadcast_to(gd1, (n,))
        gs1 = np.broadcast_to(gs1, (n,))
        # An unchanged drive (the common case) has an unchanged activation target.
        same_drive = k.theta < 1.0 and np.array_equal(gd0, gd1) and np.array_equal(gs0, gs1)
        tail = []
        evals = 0
        ring = self.z_ring
        if self.history and not np.array_equal(z0[:, ::HISTORY_PROBE],
                                               ring[0][:, ::HISTORY_PROBE]):
            self.history = 0  # the state is not the one the last step left
        self.z1 = ring[3]  # the oldest: no longer part of the history
        self.cooldown = max(0, self.cooldown - 1)
        prior = (ring[1], ring[2]) if (self.history >= 3 and n >= EXTRAPOLATE_SPINDLES
                                       and not self.cooldown) else None
        for j0 in range(0, n, CHUNK_SPINDLES):
            j1 = min(n, j0 + CHUNK_SPINDLES)
            b = self.blocks[j1 - j0]
            cols = slice(j0, j1)
            self._setup(b, cols, T0[:, cols], v0[:, cols], z0[:, cols], f0[:, cols],
                        L0[cols], L1[cols], gd0[cols], gs0[cols], gd1[cols], gs1[cols],
                        same_drive, guess=prior is None)
            if prior is not None:
                z, tmp = b.rows["z"], b.rows["tmp"]
                np.subtract(z0[:, cols], prior[0][:, cols], out=tmp)
                np.multiply(tmp, 3.0, out=tmp)
                np.add(tmp, prior[1][:, cols], out=z)
            clip = _needs_clip(b.flat, k)
            if clip:
                _bound_guess(b.flat, k)
            left, iterations = _newton_block(b, k, clip)
            evals += iterations
            if left is not None:
                rows, idx = np.divmod(left, b.w)
                f = b.flat
                tail.append((rows * n + (idx + j0), z0[rows, idx + j0], b.blend_exp[left],
                             *(x[left] for x in (
                                 f["z"], f["p0"], f["rhs"], f["cM"], f["cD"], f["A"],
                                 b.th_h_KSR, *((f["power"], f["three_over_a"], f["w_coef"])
                                               if not k.a_is_03 else ())))))
            self._finish(b, cols)
        if tail:
            self._finish_tail(tail, restart=prior is not None)
        _check_finite(self.T1, self.v1, k.h)
        self.z_ring = [ring[3], ring[0], ring[1], ring[2]]
        self.history += 1
        if prior is not None and evals > EXTRAPOLATE_MAX_ITER * len(range(0, n, CHUNK_SPINDLES)):
            self.cooldown = EXTRAPOLATE_COOLDOWN  # rough inputs: the frozen guess does better
        return self.T1, self.v1, self.z1, self.f1

    def _setup(self, b, cols, T0, v0, z0, f0, L0, L1, gd0, gs0, gd1, gs1, same_drive,
               guess=True):
        """Everything known at the start of the step, and (with ``guess``) the frozen-factor
        guess. Wide blocks go fibre row by fibre row (the constants are then Python floats,
        cheaper to apply than broadcast columns); narrow ones all rows at once with (3, 1)
        columns (fewer calls)."""
        k = self.k
        old = k.theta < 1.0
        r = b.rows
        mul, add, sub = np.multiply, np.add, np.subtract
        dL = sub(L1, L0, out=b.dL)
        by_row = b.w >= ROW_BY_ROW_SPINDLES
        gp1 = _drive_powers(gd1, gs1, k, b.gp1, all_rows=not by_row)
        gp0 = (None if same_drive or not old
               else _drive_powers(gd0, gs0, k, b.gp0, all_rows=not by_row))
        if by_row:
            groups = [(i, k.fibre[i], k.lagged[i], gp1[k.drive_row[i]],
                       None if gp0 is None else gp0[k.drive_row[i]]) for i in range(3)]
        else:
            # instantaneous fibres: keep = from_a0 = 0, from_a1 = 1 give f1 = a1 exactly
            groups = [(slice(None), k.fibre_columns, True, gp1, gp0)]
        for i, constants, lagged, g, g0 in groups:
            (keep, from_a0, from_a1, KSR, inv_KSR, A_v0, p0_v0, LR, KPR, rhs_v0, rhs_dL,
             rhs_f0, rhs_f1, rhs_const, c_mid, c_half, beta0_old, beta_drive_old, cM0, cMd,
             cD0, cDd, inv_a2, _, blend_exp, freq_p, _) = constants
            T, v, z0i, f = T0[i], v0[i], z0[i], f0[i]
            tmp, a1 = r["tmp"][i], r["a1"][i]
            f1 = self.f1[i, cols]
            if lagged:
                add(g, freq_p, out=a1)
                np.divide(g, a1, out=a1)
                mul(f, keep, out=f1)
                if old and same_drive:
                    mul(a1, from_a0 + from_a1, out=tmp)
                    add(f1, tmp, out=f1)
                else:
                    if old:
                        add(g0, freq_p, out=tmp)
                        np.divide(g0, tmp, out=tmp)
                        mul(tmp, from_a0, out=tmp)
                        add(f1, tmp, out=f1)
                    mul(a1, from_a1, out=tmp)
                    add(f1, tmp, out=f1)
            else:
                add(g, freq_p, out=tmp)
                np.divide(g, tmp, out=f1)
            cM, cD = r["cM"][i], r["cD"][i]
            mul(f1, cMd, out=cM)
            add(cM, cM0, out=cM)
            mul(f1, cDd, out=cD)
            add(cD, cD0, out=cD)
            q0, A, p0, rhs = r["q"][i], r["A"][i], r["p0"][i], r["rhs"][i]
            sub(L0, LR, out=q0)
            mul(T, inv_KSR, out=tmp)
            sub(q0, tmp, out=q0)
            mul(dL, KSR, out=A)
            add(A, T, out=A)
            mul(T, inv_a2, out=rhs)
            mul(v, rhs_v0, out=tmp)
            add(rhs, tmp, out=rhs)
            mul(dL, rhs_dL, out=tmp)
            add(rhs, tmp, out=rhs)
            mul(f1, rhs_f1, out=tmp)
            add(rhs, tmp, out=rhs)
            az, sq, cb = r["az"][i], r["sq"][i], r["cb"][i]
            np.abs(z0i, out=az)
            mul(z0i, z0i, out=sq)
            if old:
                mul(v, A_v0, out=tmp)
                sub(A, tmp, out=A)
                mul(v, p0_v0, out=p0)
                add(p0, q0, out=p0)
                mul(f, rhs_f0, out=tmp)
                add(rhs, tmp, out=rhs)
                # (KPR + D0)*q0, D0 the damping factor of the force at the start
                mul(z0i, c_mid, out=cb)
                mul(az, c_half, out=tmp)
                add(cb, tmp, out=cb)
                mul(f, beta_drive_old, out=tmp)
                add(tmp, beta0_old, out=tmp)
                mul(cb, tmp, out=cb)
                mul(cb, sq, out=cb)
                add(cb, KPR, out=cb)
                mul(cb, q0, out=cb)
                if q0.min() <= 0.0:  # no damping where the polar region is not longer than R
                    np.copyto(cb, q0 * KPR, where=q0 <= 0.0)
            else:
                p0[...] = q0
                mul(q0, KPR, out=cb)
            add(rhs, rhs_const, out=rhs)
            sub(rhs, cb, out=rhs)
            if guess:
                _frozen_guess(z0i, az, sq, rhs, cM, cD, p0, blend_exp, k.a_is_03,
                              {name: r[name][i] for name in ("z", "t9", "g", "dg", "tmp")},
                              b.same_sign[i])

    def _finish(self, b, cols):
        """v1, T1 and z1 of a block from its last Newton iteration. That iteration moved z by
        dz (|dz| <= NEWTON_TOL_Z wherever the block converged; the tail rewrites the rest), so
        v(z) = v(z_prev) - v'(z_prev)*dz is exact to O(dz^2): below 1e-16 L0/s, v's rounding."""
        r = b.rows
        k = self.k
        v1 = self.v1[:, cols]
        np.multiply(r["dv"], r["dz"], out=r["tmp"])
        np.subtract(r["w"], r["tmp"], out=v1)
        for i in range(3):
            T1 = self.T1[i, cols]
            np.multiply(v1[i], k.th_h_KSR_floats[i], out=T1)
            np.subtract(r["A"][i], T1, out=T1)
        self.z1[:, cols] = r["z"]

    def _finish_tail(self, tail, restart):
        """Newton to convergence on the fibres the blocks handed over. With ``restart`` (their
        guess was extrapolated) they start again from the frozen-factor guess: an
        extrapolation that overshoots toward or across v = 0 leaves Newton far above a small
        root, where it creeps (each step removes only ~1/10 of the excess of z^10)."""
        idx, z0, blend_exp, z, p0, rhs, cM, cD, A, th_h_KSR, *exponents = (
            np.concatenate(x) for x in zip(*tail, strict=True))
        s = {name: np.empty(z.size) for name in _Block.NAMES}
        k = self.k
        if restart:
            s["z"] = z
            _frozen_guess(z0, np.abs(z0), z0 * z0, rhs, cM, cD, p0, blend_exp, k.a_is_03, s,
                          np.empty(z.size, dtype=bool))
        s["z"] = z
        if exponents:
            s["power"], s["three_over_a"], s["w_coef"] = exponents
        s["p0"], s["rhs"] = p0, rhs
        clip = _needs_clip(s, k)
        if clip:
            _bound_guess(s, k)
        _newton_loop(z, p0, rhs, cM, cD, k, s, first=0, clip=clip)
        v = _velocity_into(z, s["az"], s["t9"], s["w"], k, s.get("power"))
        self.z1.reshape(-1)[idx] = z
        self.v1.reshape(-1)[idx] = v
        self.T1.reshape(-1)[idx] = A - th_h_KSR * v


def _frozen_guess(z0, az, sq, rhs, cM, cD, p0, blend_exp, a_is_03, s, same_sign):
    """The Newton guess from the start of the step, into ``s["z"]``; ``az`` and ``sq`` hold
    |z0| and z0^2, ``s`` scratch arrays "t9", "g", "dg", "tmp" shaped like z0, ``same_sign``
    a bool array of that shape.

    g with |v|/|z^3| frozen at its previous value |z0|^7 (a = 0.3) is linear in z^3; its root
    already has the right sign and, near v = 0 and in holds where the trapezoidal rule rings,
    the right size, which the previous z has not.
    """
    mul, add = np.multiply, np.add
    a2t, slope, blend, z, tmp = s["t9"], s["g"], s["dg"], s["z"], s["tmp"]
    if a_is_03:
        mul(sq, sq, out=a2t)
        mul(a2t, sq, out=a2t)
        mul(a2t, az, out=a2t)
    else:
        np.power(az, blend_exp * 3.0, out=a2t)
    np.copysign(cD, rhs, out=slope)
    add(slope, cM, out=slope)
    np.maximum(p0, 0.0, out=blend)
    mul(slope, blend, out=slope)
    add(slope, a2t, out=slope)
    np.divide(rhs, slope, out=z)
    np.cbrt(z, out=z)
    # The frozen factor's error: log z_guess - log z ~ e*s*(log z - log z0), e the exponent
    # of |z| in it (7/3 for a = 0.3) and s the share of the |v| term in the slope; solving
    # that to first order blends the guess toward z0 by e*s/(1 + e*s). Only where z0 and the
    # guess share a sign (v does not reverse).
    mul(a2t, blend_exp, out=blend)
    add(slope, blend, out=tmp)
    np.divide(blend, tmp, out=blend)
    mul(z0, z, out=tmp)
    np.greater(tmp, 0.0, out=same_sign)
    mul(blend, same_sign, out=blend)
    np.subtract(z0, z, out=tmp)
    mul(tmp, blend, out=tmp)
    add(z, tmp, out=z)
    return z


def _drive_powers(gd, gs, k, out, all_rows=False):
    """g^p of each fibre's drive into the rows of ``out`` that ``k.drive_row`` names (into
    every row with ``all_rows``)."""
    for row, (g, p) in enumerate(zip((gd, gs, gs), k.p, strict=True)):
        if row in k.drive_row:
            with np.errstate(over="ignore"):
                if p == 2.0:
                    np.multiply(g, g, out=out[row])
                else:
                    np.power(g, p, out=out[row])
            np.minimum(out[row], MAX_DRIVE_POWER, out=out[row])
        elif all_rows:
            out[row] = out[k.drive_row[row]]
    return out


def _velocity_into(z, az, t, w, k, power=None):
    """v = sgn(z)|z|^(3/a) into ``w``, with |z| in ``az`` and |z|^(3/a - 1) in ``t``
    (``power`` holds 3/a - 1 unless a = 0.3, where it is z^8*|z|: no fractional power)."""
    np.abs(z, out=az)
    if k.a_is_03:
        np.multiply(z, z, out=t)
        np.multiply(t, t, out=t)
        np.multiply(t, t, out=t)
        np.multiply(t, az, out=t)
    else:
        np.power(az, power, out=t)
    np.multiply(t, z, out=w)
    return w


def _needs_clip(s, k) -> bool:
    """Whether the new polar region of any fibre in ``s`` (flat arrays "p0", "rhs") may end
    no longer than R, where the damping's clip at 0 enters the step equation. At the root
    |w| <= |rhs| (the damping term has the sign of w), so q = p0 + theta*h*w >= 0 wherever
    p0 > theta*h*|rhs|: everywhere but near the short end of the length range (three
    reductions per block)."""
    rhs = s["rhs"]
    return bool(s["p0"].min() <= k.th_h * max(rhs.max(), -rhs.min()))


def _bound_guess(s, k) -> None:
    """Replace guesses beyond the root's bound |z| <= |rhs|^(a/3) (and NaN ones: with v = 0
    and p0 <= 0 the frozen-factor guess has no slope) by the bound, in ``s["z"]``."""
    z, rhs = s["z"], s["rhs"]
    exponent = 0.1 if k.a_is_03 else 1.0 / s["three_over_a"]
    bound = np.abs(rhs) ** exponent
    far = ~(np.abs(z) <= bound)
    z[far] = np.copysign(bound, rhs)[far]


def _newton_block(b, k, clip=False):
    """Newton on one block; returns (the flat indices handed to the tail or None, the number
    of iterations)."""
    f = b.flat
    return _newton_loop(f["z"], f["p0"], f["rhs"], f["cM"], f["cD"], k, f,
                        first=NEWTON_FULL_ITER - 1, moving=b.moving, clip=clip)


def _newton_loop(z, p0, rhs, cM, cD, k, s, first, moving=None, clip=False):
    """Newton's method on the step equation for z, in place, until every |dz| <= 1e-9.

    The unknown is z = sgn(v)|v|^(a/3): the damping sgn(v)|v|^a is z^3 and v = sgn(z)|z|^(3/a)
    (z^10 for a = 0.3), both polynomials, so no iteration evaluates a fractional power. With
    w = v1 and T1 = A - theta*h*KSR*w (A holds everything known, see :class:`_StepConstants`),
    the step equation M*(v1 - v0)/h = (1 - theta)*F0 + theta*F1 divided by a2 reads

        g(z) = w + Cb(z)*z^3*(p0 + theta*h*w) - rhs = 0

    with Cb = theta*C*beta1/a2 = cM + cD*sgn(z) (C = CL for z > 0, CS else) and p0 the new
    polar length minus R at w = 0. g rises monotonically (convex for z > 0, concave below)
    wherever the polar region is longer than R, so Newton converges after at most one
    overshoot; steps are capped at NEWTON_MAX_DZ, which also covers g' = 0 at z = 0.

    With ``clip`` the damping's factor q (the new polar length minus R) is clipped at 0, the
    model's rule (see the module docstring): where q <= 0, g = w - rhs. g then rises
    monotonically everywhere; without ``clip`` the caller has made sure q > 0 at the root
    (:func:`_needs_clip`), where both equations agree.

    ``s`` holds scratch arrays shaped like z. From iteration ``first`` on, if at most
    1/TAIL_FRACTION of the fibres still move (|dz| > tolerance), their flat indices are
    returned and the caller finishes them together with other blocks' (a few fibres whose v
    reverses need more iterations than the rest); else None once all have converged. The
    second value returned is the number of iterations.
    """
    mul, add = np.multiply, np.add
    # 12 arrays in all, so that a block's stay in the core's cache: dz holds g before it
    # turns into dz, t = |z|^(3/a - 1) turns into v'(z) = (3/a)*t, dg is scratch until g'
    t, w, az, cb, dz, dg, p3 = (s[name] for name in ("dv", "w", "az", "cb", "dz", "dg", "p3"))
    th_h = k.th_h
    dv_factor = 10.0 if k.a_is_03 else s["three_over_a"]
    power = None if k.a_is_03 else s["power"]
    # g' = v'(z)*(1 + theta*h*phi) + 3*cb*q with phi = cb*z and v' = (3/a)|z|^(3/a - 1), so
    # phi*v' = (3/a)*cb*w and g' = v' + cb*(3*p0 + (3 + 3/a)*theta*h*w); 3*p0 is fixed.
    mul(p0, 3.0, out=p3)
    w_coef = s["w_coef"] if not k.a_is_03 else 13.0 * th_h
    for iteration in range(NEWTON_MAX_ITER):
        _velocity_into(z, az, t, w, k, power)
        # cb = Cb*z^2 with Cb = theta*C*beta1 (C = CL for z > 0, CS else)
        mul(cM, z, out=cb)
        mul(cD, az, out=dg)
        add(cb, dg, out=cb)
        mul(cb, z, out=cb)
        # g = w + cb*z*q - rhs with q = p0 + theta*h*w
        mul(w, th_h, out=dz)
        add(dz, p0, out=dz)
        if clip:
            undamped = dz <= 0.0
            np.maximum(dz, 0.0, out=dz)
        mul(dz, cb, out=dz)
        mul(dz, z, out=dz)
        add(dz, w, out=dz)
        np.subtract(dz, rhs, out=dz)
        mul(t, dv_factor, out=t)
        mul(w, w_coef, out=dg)
        add(dg, p3, out=dg)
        mul(dg, cb, out=dg)
        add(dg, t, out=dg)
        if clip:
            np.copyto(dg, t, where=undamped)
        np.maximum(dg, 1e-300, out=dg)
        np.divide(dz, dg, out=dz)
        hi = dz.max()
        lo = dz.min()
        if hi > NEWTON_MAX_DZ or lo < -NEWTON_MAX_DZ:
            np.clip(dz, -NEWTON_MAX_DZ, NEWTON_MAX_DZ, out=dz)
        np.subtract(z, dz, out=z)
        if hi <= NEWTON_TOL_Z and lo >= -NEWTON_TOL_Z:
            return None, iteration + 1
        if moving is not None and iteration >= first:
            np.abs(dz, out=dg)
            np.greater(dg, NEWTON_TOL_Z, out=moving)
            left = np.flatnonzero(moving)
            if left.size <= moving.size // TAIL_FRACTION:
                # none left: the only fibres not converged are NaN, which the finite check
                # after the step reports
                return (left if left.size else None), iteration + 1
    raise FloatingPointError(
        f"implicit spindle step did not converge in {NEWTON_MAX_ITER} iterations "
        f"(last change in z {max(hi, -lo):.3g}); state left unchanged"
    )


SMALL_N = 8
"""Up to this many spindles the step runs on Python floats, fibre by fibre: for a few
spindles numpy's per-call overhead costs more than the arithmetic."""


def _as_floats(x, n: int) -> list[float]:
    """A scalar or an array broadcastable to (n,) as a list of n floats."""
    if isinstance(x, np.ndarray):
        if x.shape == (n,):
            return x.tolist()
        if x.size == 1:
            return [float(x.reshape(-1)[0])] * n
        return np.broadcast_to(x, (n,)).tolist()
    return [float(x)] * n


def _advance_small(state, L1, gd1, gs1, h, theta, c):
    """:func:`advance` for a few spindles, on Python floats (same arithmetic, per fibre)."""
    k = _step_constants(c, h, theta)
    n = state.n
    T0 = state.tension_FU.tolist()
    v0 = state.polar_velocity_L0_s.tolist()
    z0 = state.velocity_root.tolist()
    f0 = state.activation.tolist()
    L0 = state.length_L0.tolist()
    gd0 = state.gamma_dyn_pps.tolist()
    gs0 = state.gamma_stat_pps.tolist()
    L1, gd1, gs1 = (_as_floats(x, n) for x in (L1, gd1, gs1))
    out = [_step_floats(k, T0[i], v0[i], z0[i], f0[i], L0[i], gd0[i], gs0[i], L1[i], gd1[i],
                        gs1[i]) for i in range(n)]
    # (n spindles) x (T, v, z, f) x 3 fibres -> four (3, n) arrays
    arr = np.array(out).transpose(1, 2, 0)
    return arr[0], arr[1], arr[2], arr[3]


def _drive_powers_floats(gd: float, gs: float, k: _StepConstants) -> list[float]:
    return [min(g * g if p == 2.0 else _float_power(g, p), MAX_DRIVE_POWER)
            for g, p in zip((gd, gs, gs), k.p, strict=True)]


def _float_power(g: float, p: float) -> float:
    try:
        return g**p
    except OverflowError:  # Python floats raise where numpy gives inf
        return math.inf


def _step_floats(k, T0, v0, z0, f0, L0, gd0, gs0, L1, gd1, gs1):
    """One implicit step of one spindle on floats; returns the new (T, v, z, f), each a list
    over the three fibres. The arithmetic is that of the vectorised step, term by term."""
    old = k.theta < 1.0
    same_drive = gd0 == gd1 and gs0 == gs1
    gp1 = _drive_powers_floats(gd1, gs1, k)
    gp0 = None if same_drive or not old else _drive_powers_floats(gd0, gs0, k)
    dL = L1 - L0
    T1, v1, z1, f1 = [], [], [], []
    for i in range(3):
        (keep, from_a0, from_a1, KSR, inv_KSR, A_v0, p0_v0, LR, KPR, rhs_v0, rhs_dL,
         rhs_f0, rhs_f1, rhs_const, c_mid, c_half, beta0_old, beta_drive_old, cM0, cMd,
         cD0, cDd, inv_a2, th_h_KSR, blend_exp, freq_p, three_over_a) = k.fibre[i]
        T, v, z, f = T0[i], v0[i], z0[i], f0[i]
        g = gp1[i]
        if k.lagged[i]:
            a1 = g / (g + freq_p)
            fn = f * keep
            if old and same_drive:
                fn = fn + a1 * (from_a0 + from_a1)
            else:
                if old:
                    g = gp0[i]
                    fn = fn + g / (g + freq_p) * from_a0
                fn = fn + a1 * from_a1
        else:
            fn = g / (g + freq_p)
        cM = fn * cMd + cM0
        cD = fn * cDd + cD0
        q0 = (L0 - LR) - T * inv_KSR
        A = dL * KSR + T
        rhs = T * inv_a2 + v * rhs_v0 + dL * rhs_dL + fn * rhs_f1
        az = abs(z)
        sq = z * z
        if old:
            A = A - v * A_v0
            p0 = v * p0_v0 + q0
            rhs = rhs + f * rhs_f0
            if q0 > 0.0:
                cb = ((z * c_mid + az * c_half) * (f * beta_drive_old + beta0_old) * sq
                      + KPR) * q0
            else:  # no damping where the polar region is not longer than R
                cb = q0 * KPR
        else:
            p0 = q0
            cb = q0 * KPR
        rhs = rhs + rhs_const - cb
        a2t = sq * sq * sq * az if k.a_is_03 else az ** (3.0 * blend_exp)
        slope = (math.copysign(cD, rhs) + cM) * max(p0, 0.0) + a2t
        if slope:
            zg = math.cbrt(rhs / slope)
            blend = a2t * blend_exp
            blend = blend / (slope + blend)
            z = zg + (z - zg) * blend if z * zg > 0.0 else zg
        else:
            z = math.nan
        # Where the new polar region may end up no longer than R, the damping's clip at 0 is
        # part of the equation; |w| <= |rhs| at its root (the damping has the sign of w).
        clip = p0 <= k.th_h * abs(rhs)
        if clip:
            bound = abs(rhs) ** (1.0 / three_over_a)
            if not abs(z) <= bound:  # also a NaN guess (no slope at v = 0, p0 <= 0)
                z = math.copysign(bound, rhs)
        z = _newton_float(z, p0, rhs, cM, cD, k, three_over_a, clip)
        az = abs(z)
        if k.a_is_03:
            sq = z * z
            t = sq * sq
            t = t * t * az
        else:
            t = az ** (three_over_a - 1.0)
        w = t * z
        T1.append(A - w * th_h_KSR)
        v1.append(w)
        z1.append(z)
        f1.append(fn)
    if not all(math.isfinite(x) for x in T1 + v1):
        raise FloatingPointError(
            "the spindle step produced a non-finite tension or velocity; state left unchanged "
            f"(step {k.h!r} s)"
        )
    return T1, v1, z1, f1


def _newton_float(z, p0, rhs, cM, cD, k, three_over_a, clip=False):
    """Newton on the step equation of :func:`_newton_loop` for one fibre; with ``clip`` the
    damping's polar-length factor q is clipped at 0 (where q <= 0, g = w - rhs)."""
    th_h = k.th_h
    th_h_10 = 10.0 * th_h
    a_is_03 = k.a_is_03
    power = three_over_a - 1.0
    dv_scale = three_over_a / 10.0
    dz = math.inf
    for _ in range(NEWTON_MAX_ITER):
        az = abs(z)
        if a_is_03:
            sq = z * z
            t = sq * sq
            t = t * t * az
        else:
            t = az**power
        w = t * z
        cb = (cM * z + cD * az) * z
        phi = cb * z
        q = w * th_h + p0
        if clip and q <= 0.0:
            g = w - rhs
            dg = 10.0 * t if a_is_03 else three_over_a * t
        else:
            g = phi * q + w - rhs
            dg = phi * th_h_10 + 10.0
            if not a_is_03:
                dg = dg * dv_scale
            dg = dg * t + cb * q * 3.0
        dz = g / max(dg, 1e-300)  # a NaN dg stays NaN (max keeps its first argument)
        if dz > NEWTON_MAX_DZ:
            dz = NEWTON_MAX_DZ
        elif dz < -NEWTON_MAX_DZ:
            dz = -NEWTON_MAX_DZ
        z = z - dz
        if abs(dz) <= NEWTON_TOL_Z:
            return z
    raise FloatingPointError(
        f"implicit spindle step did not converge in {NEWTON_MAX_ITER} iterations "
        f"(last change in z {abs(dz):.3g}); state left unchanged"
    )


def _afferents_small(T: np.ndarray, L: np.ndarray, c: _Columns):
    """:func:`_afferents` on Python floats for a few spindles (same formula)."""
    n = T.shape[1]
    columns_of_T = T.T.tolist()
    lengths = _as_floats(L, n)
    rates = [_afferents_one(columns_of_T[j], lengths[j], c) for j in range(n)]
    return np.array([r[0] for r in rates]), np.array([r[1] for r in rates])


def _afferents_one(T: list[float], L: float, c: _Columns) -> tuple[float, float]:
    """Ia and II (pps) of one spindle from its three fibre tensions, on floats (the
    arithmetic of :func:`_afferents`)."""
    (g0, n0), (g1, n1), (g2, n2) = c.primary_lin
    (a1, b1, c1), (a2, b2, c2) = c.secondary_lin
    x = max(T[0] * g0 - n0, 0.0)
    y = max(T[1] * g1 - n1, 0.0) + max(T[2] * g2 - n2, 0.0)
    ia = max(x, y) + min(x, y) * c.S_float
    ii = max(T[1] * a1 + L * b1 + c1, 0.0) + max(T[2] * a2 + L * b2 + c2, 0.0)
    return ia, ii


def _workspace(state: SpindleState, k: _StepConstants) -> _Workspace:
    """The reusable buffers of ``state`` (kept on the state object, not a module global)."""
    ws = state.__dict__.get("_workspace")
    if ws is None or ws.n != state.n:
        ws = state.__dict__["_workspace"] = _Workspace(state.n)
    ws.prepare(k)
    return ws
