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

The implicit settings solve, per fibre and step, one scalar equation that is monotone in the
new v. It is solved for z = sgn(v)|v|^(a/3) instead of v: the damping sgn(v)|v|^a is z^3 and
v is z^10 (a = 0.3), so Newton's method meets no infinite slope (as it would at v = 0) and
evaluates no fractional power. The state keeps z beside v.

Shapes: public state arrays have a leading spindle axis, ``(n, 3)`` with columns
(bag1, bag2, chain). They are transposed views of fibre-major ``(3, n)`` buffers, the layout
the arithmetic runs on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spindle.methods import Method, get_method
from spindle.params import CAT, SpindleParams

LENGTH_RANGE_L0 = (0.5, 1.5)
"""Accepted normalised fascicle lengths. Below ~0.5 L0 the polar region becomes shorter than
the damping's reference length R and the model's damping changes sign (it is then no longer a
damper); above 1.5 L0 the model was never fitted."""

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


def activation_target(drive_pps: np.ndarray, freq_pps: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Steady-state fusimotor activation g^p / (g^p + freq^p) (dimensionless)."""
    if np.all(p == 2.0):
        gp = drive_pps * drive_pps
        return gp / (gp + freq_pps * freq_pps)
    gp = drive_pps**p
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


def _velocity_from_z(z: np.ndarray, c: _Columns) -> tuple[np.ndarray, np.ndarray]:
    """v = sgn(z)|z|^(3/a) and dv/dz."""
    if c.a_is_03:
        az = np.abs(z)
        z4 = z * z
        z4 *= z4
        z8az = z4 * z4
        z8az *= az
        return z8az * z, 10.0 * z8az
    az_pow = np.abs(z) ** (c.three_over_a - 1.0)
    return z * az_pow, c.three_over_a * az_pow


def _z_from_velocity(v: np.ndarray, c: _Columns) -> np.ndarray:
    return np.sign(v) * np.abs(v) ** (c.a / 3.0)


def _force(T, z, L, beta, Gamma, c):
    """M dv/dt of each fibre (FU); the damping C*beta*sgn(v)|v|^a is C*beta*z^3."""
    polar = L - c.LSR0 - T / c.KSR
    damping = np.where(z > 0, c.CL, c.CS) * beta * (z * z * z)
    return T - Gamma - c.KPR * (polar - c.LPR0) - damping * (polar - c.R)


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


def _afferents(T: np.ndarray, L: np.ndarray, c: _Columns) -> tuple[np.ndarray, np.ndarray]:
    # Every fibre's potential is clipped at 0 before they are combined (a slack fibre neither
    # excites nor inhibits the shared ending); the totals are then >= 0 by construction.
    stretch = T / c.KSR - (c.LNSR - c.LSR0)
    primary = np.maximum(c.G_pri * stretch, 0.0)
    a_dyn = primary[0]
    b_stat = primary[1] + primary[2]
    ia = np.maximum(a_dyn, b_stat) + c.S * np.minimum(a_dyn, b_stat)
    sec = c.G_sec[1:] * (
        c.X[1:] * (c.Lsec[1:] / c.LSR0[1:]) * stretch[1:]
        + (1.0 - c.X[1:]) * (c.Lsec[1:] / c.LPR0[1:])
        * (L - T[1:] / c.KSR[1:] - c.LSR0[1:] - c.LNPR[1:])
    )
    ii = np.maximum(sec, 0.0).sum(axis=0)
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
    """One theta-method step from the state to (L1, gd1, gs1), unchecked; returns new arrays.

    Nothing in ``state`` is modified: the caller commits the result once it is known to be
    finite, so a failed step leaves the state as it was.
    """
    T0 = state.tension_FU.T
    v0 = state.polar_velocity_L0_s.T
    u0 = state.velocity_root.T
    f0 = state.activation.T
    L0 = state.length_L0

    # Activation: the same theta-method on df/dt = (a* - f)/tau; instantaneous fibres take a*.
    a1 = activation_target(_drive_rows(gd1, gs1), c.freq, c.p)
    rate = h / c.tau_safe
    if theta < 1.0:
        a0 = activation_target(_drive_rows(state.gamma_dyn_pps, state.gamma_stat_pps),
                               c.freq, c.p)
        f1 = (f0 + rate * ((1.0 - theta) * (a0 - f0) + theta * a1)) / (1.0 + theta * rate)
    else:
        f1 = (f0 + rate * a1) / (1.0 + rate)
    f1[~c.lagged] = a1[~c.lagged]

    beta1 = c.beta0 + c.beta_drive * f1
    Gamma1 = c.Gamma_drive * f1
    # The exact integral of dL over the step (see module docstring).
    A = T0 + c.KSR * (L1 - L0)
    if theta == 0.0:
        F0 = _force(T0, u0, L0, c.beta0 + c.beta_drive * f0, c.Gamma_drive * f0, c)
        T1 = A - (h * c.KSR) * v0
        v1 = v0 + (h / c.M) * F0
        u1 = _z_from_velocity(v1, c)
    else:
        if theta < 1.0:
            F0 = _force(T0, u0, L0, c.beta0 + c.beta_drive * f0, c.Gamma_drive * f0, c)
            A = A - ((1.0 - theta) * h) * c.KSR * v0
        else:
            F0 = None
        T1, v1, u1 = _implicit_solve(A, v0, u0, F0, L1, beta1, Gamma1, h, theta, c)
    if not (np.isfinite(T1).all() and np.isfinite(v1).all()):
        raise FloatingPointError(
            "the spindle step produced a non-finite tension or velocity; state left unchanged "
            f"(step {h!r} s)"
        )
    return T1, v1, u1, f1


def _implicit_solve(A, v0, z0, F0, L1, beta1, Gamma1, h, theta, c):
    """Solve the theta-method's equation for the new z by Newton iteration.

    The unknown is z = sgn(v)|v|^(a/3): the damping sgn(v)|v|^a is z^3 and v = sgn(z)|z|^(3/a)
    (z^10 for a = 0.3), both polynomials, so no iteration evaluates a fractional power. With
    w = v1 and T1 = A - theta*h*KSR*w (A holds everything known), the step equation
    M*(v1 - v0)/h = (1 - theta)*F0 + theta*F1 becomes

        g(z) = a2*w + theta*Cb(z)*z^3*(p0 + theta*h*w) - rhs = 0

    with a2 = M/h + theta^2*h*k1*KSR and p0 the new polar length minus R at w = 0. g rises
    monotonically (convex for z > 0, concave below) wherever the polar region is longer than
    R, so Newton from the previous z converges after at most one overshoot; steps are capped
    at NEWTON_MAX_DZ, which also covers a start at z = 0 where g' vanishes.
    """
    KSR = c.KSR
    a2 = c.M / h + (theta * theta * h) * c.k1 * KSR
    p0 = L1 - c.LSR0 - c.R - A / KSR
    th_h = theta * h
    rhs = (c.M / h) * v0 + theta * (c.k1 * A - Gamma1 - c.KPR * (L1 - c.LSR0 - c.LPR0))
    if F0 is not None:
        rhs += (1.0 - theta) * F0
    # Cb(z)*z^3 = cS*z^3 + dC*max(z, 0)*z^2 with cS = theta*CS*beta, dC = theta*(CL-CS)*beta.
    cS = (theta * c.CS) * beta1
    dC = (theta * (c.CL - c.CS)) * beta1

    # Starting guess: g with |v|/|u| frozen at its previous value |z0|^7 (for a = 0.3) is
    # linear in u = z^3; its root already has the right sign and, in holds where the
    # trapezoidal rule rings, the right size, which the previous z has not.
    z0_7 = z0 * z0
    z0_7 *= z0_7 * z0_7 * np.abs(z0) if c.a_is_03 else np.abs(z0) ** (c.three_over_a - 3.0)
    slope = a2 * z0_7 + np.where(rhs > 0, cS + dC, cS) * np.maximum(p0, 0.0)
    z = np.cbrt(rhs / slope)
    active = None
    dz = np.zeros_like(z)
    for iteration in range(NEWTON_MAX_ITER):
        if active is None and iteration >= NEWTON_FULL_ITER and c.a_is_03:
            # Once few fibres are still moving (e.g. a polar velocity changing sign), they go
            # on alone; gathering them costs more than it saves while many are.
            moving = np.abs(dz) > NEWTON_TOL_Z
            if np.count_nonzero(moving) > moving.size // 8:
                moving = None
        else:
            moving = None
        if moving is not None:
            active = np.nonzero(moving)
            z_all = z
            z = z_all[active]
            a2, p0, rhs, cS, dC = (np.broadcast_to(x, z_all.shape)[active]
                                   for x in (a2, p0, rhs, cS, dC))
        w, dw = _velocity_from_z(z, c)
        z2 = z * z
        zp = np.maximum(z, 0.0)
        phi = cS * (z2 * z) + dC * (zp * z2)
        dphi = 3.0 * (cS * z2 + dC * (zp * z))
        q = p0 + th_h * w
        g = a2 * w + phi * q - rhs
        dg = a2 * dw + dphi * q + th_h * phi * dw
        dz = g / np.maximum(dg, 1e-300)
        np.minimum(dz, NEWTON_MAX_DZ, out=dz)
        np.maximum(dz, -NEWTON_MAX_DZ, out=dz)
        z = z - dz
        if z.size == 0 or np.abs(dz).max() <= NEWTON_TOL_Z:
            break
    else:
        raise FloatingPointError(
            f"implicit spindle step did not converge in {NEWTON_MAX_ITER} iterations "
            f"(last change in z {np.abs(dz).max():.3g}); state left unchanged"
        )
    if active is not None:
        z_all = z_all.copy()
        z_all[active] = z
        z = z_all
    v1, _ = _velocity_from_z(z, c)
    T1 = A - th_h * KSR * v1
    return T1, v1, z
