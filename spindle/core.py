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
Implementations: :func:`plain_advance` is the step written plainly from these equations
(Newton on the step residual itself); :func:`advance` runs it for the explicit setting and,
for the implicit ones, one of two fast implementations of the same equation, which agree
with it to rounding: :mod:`spindle.float_step` (Python floats, a few spindles) and
:mod:`spindle.batch_step` (numpy blocks in cache, any number).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spindle.batch_step import advance_batched
from spindle.fibre_constants import (
    MAX_DRIVE_POWER,
    FibreColumns,
    check_finite,
    columns,
    spindle_step_constants,
    step_constants,
)
from spindle.float_step import SMALL_N, advance_small, afferents_one, as_floats
from spindle.methods import Method, get_method
from spindle.number_rule import real_array, real_scalar
from spindle.params import CAT, SpindleParams

__all__ = [
    "LENGTH_RANGE_L0", "MAX_DRIVE_POWER", "MAX_SPEED_L0_S", "SLEW_LIMIT_L0_S", "SMALL_N",
    "STATE_FIELDS", "SpindleState",
    "activation_target", "advance", "afferents", "afferents_from_tension", "check_inputs",
    "check_speed", "check_step", "columns", "commit", "equilibrium_state", "force",
    "plain_advance", "step",
]

LENGTH_RANGE_L0 = (0.5, 1.5)
"""Accepted normalised fascicle lengths. Below ~0.5 L0 the polar region becomes shorter than
the damping's reference length R even without drive (the damping is clipped there, see the
module docstring, and the model stops describing a spindle); above 1.5 L0 the model was never
fitted."""

MAX_SPEED_L0_S = 10.0
"""Largest accepted |dL/dt|: about the maximum shortening velocity of fast muscle fibres."""

SLEW_LIMIT_L0_S = 8.0
"""The default slew limit on the lengths a chain or a spindle bank feeds its spindles (L0/s):
1000 deg/s of elbow motion for the brachialis, above the servo's 684 deg/s no-load speed and
below :data:`MAX_SPEED_L0_S`; a faster change (a jump after a gap, a spike) is limited to it."""

STATE_FIELDS = ("tension_FU", "polar_velocity_L0_s", "velocity_root", "activation",
                "length_L0", "gamma_dyn_pps", "gamma_stat_pps")
"""The arrays of a :class:`SpindleState`, in its fields' order."""

AFFERENT_CHUNK = 8192
"""Spindles per block of :func:`afferents_from_tension` (its temporaries stay in cache)."""

PLAIN_NEWTON_TOL_Z = 1e-13
PLAIN_NEWTON_MAX_ITER = 500

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
        return tuple(getattr(self, name) for name in STATE_FIELDS)


def _fibre_major(buffer_3n: np.ndarray) -> np.ndarray:
    """A (n, 3) view of a C-contiguous (3, n) buffer."""
    return np.ascontiguousarray(buffer_3n).T


def _as_spindle_vector(name: str, value: object, n: int | None = None) -> np.ndarray:
    arr = real_array(name, value)
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


def check_step(step_s: float, method: Method, name: str = "step") -> float:
    """``step_s`` as a Python float (the rule of :mod:`spindle.number_rule`); refuse a non-positive
    step or one beyond the method's limit."""
    h = real_scalar(name, step_s, low=0.0, low_open=True)
    if h > method.max_step_s * (1 + 1e-9):
        raise ValueError(
            f"{name}={step_s!r} s exceeds the {method.name} limit of {method.max_step_s!r} s"
        )
    return h



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



def _z_from_velocity(v: np.ndarray, c: FibreColumns) -> np.ndarray:
    return np.sign(v) * np.abs(v) ** (c.a / 3.0)


def _velocity_from_z(z: np.ndarray, c: FibreColumns) -> np.ndarray:
    return np.sign(z) * np.abs(z) ** (3.0 / c.a)


def force(T: np.ndarray, z: np.ndarray, L: np.ndarray, f: np.ndarray, c: FibreColumns
          ) -> np.ndarray:
    """M dv/dt of each fibre (FU), (3, n), at tension T, z, length L and activation f; the
    damping C*beta*sgn(v)|v|^a is C*beta*z^3, times the polar length beyond R clipped at 0
    (see the module docstring)."""
    beta, Gamma = c.beta0 + c.beta_drive * f, c.Gamma_drive * f
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
    arrays = [real_array(name, x) for name, x in (
        ("length_L0", length_L0), ("gamma_dyn_pps", gamma_dyn_pps),
        ("gamma_stat_pps", gamma_stat_pps))]
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
    return afferents_from_tension(state.tension_FU.T, state.length_L0, columns(params))


def afferents_from_tension(T: np.ndarray, L: np.ndarray | float,
                           c: FibreColumns) -> tuple[np.ndarray, np.ndarray]:
    """Ia and II (pps), each (n,), of fibre tensions T (3, n) at fascicle lengths L (n,).

    Every fibre's potential is clipped at 0 before they are combined (a slack fibre neither
    excites nor inhibits the shared ending); the totals are then >= 0 by construction. Each
    potential is linear in the fibre's T (and the secondary's in L too); it is evaluated in
    that multiplied-out form (:attr:`FibreColumns.primary_lin`, :attr:`FibreColumns.secondary_lin`).
    """
    n = T.shape[1]
    if n <= SMALL_N:
        # on floats: 4.2x the numpy form at n = 1, 2.4x at 2 (the chain's two spindles),
        # 1.2x at 8 (`bench_spindle.py --paths`, 2026-12-01)
        return _afferents_floats(T, L, c)
    if n <= AFFERENT_CHUNK:
        return _afferents_block(T, L, c)
    # in blocks whose temporaries stay in cache: the whole step at n = 65536 takes 4% less
    # than with one pass (19.2 vs 20.1 ms, `bench_spindle.py --paths`, 2026-12-01)
    L = np.broadcast_to(L, (n,))
    ia, ii = np.empty(n), np.empty(n)
    for j0 in range(0, n, AFFERENT_CHUNK):
        cols = slice(j0, j0 + AFFERENT_CHUNK)
        ia[cols], ii[cols] = _afferents_block(T[:, cols], L[cols], c)
    return ia, ii


def _afferents_block(T: np.ndarray, L, c: FibreColumns) -> tuple[np.ndarray, np.ndarray]:
    (g0, n0), (g1, n1), (g2, n2) = c.primary_lin
    (a1, b1, c1), (a2, b2, c2) = c.secondary_lin
    dynamic = np.maximum(T[0] * g0 - n0, 0.0)
    static = np.maximum(T[1] * g1 - n1, 0.0) + np.maximum(T[2] * g2 - n2, 0.0)
    ia = np.maximum(dynamic, static) + np.minimum(dynamic, static) * c.S
    ii = (np.maximum(T[1] * a1 + L * b1 + c1, 0.0)
          + np.maximum(T[2] * a2 + L * b2 + c2, 0.0))
    return ia, ii


def _afferents_floats(T: np.ndarray, L, c: FibreColumns) -> tuple[np.ndarray, np.ndarray]:
    """:func:`afferents_from_tension` spindle by spindle on Python floats (few spindles)."""
    n = T.shape[1]
    lengths = as_floats(L, n)
    rates = [afferents_one(tension, lengths[j], c) for j, tension in enumerate(T.T.tolist())]
    return np.array([r[0] for r in rates]), np.array([r[1] for r in rates])


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
    dt_s = check_step(dt_s, m, "dt_s")
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
    return afferents_from_tension(new[0], L, c)


def commit(state: SpindleState, new, L, gd, gs, where: np.ndarray | None = None) -> None:
    """Write the result of :func:`advance` into ``state``; with ``where`` ((n,) bool), only
    into those spindles."""
    T, v, u, f = new
    if where is not None:
        for target, value in ((state.tension_FU.T, T), (state.polar_velocity_L0_s.T, v),
                              (state.velocity_root.T, u), (state.activation.T, f),
                              (state.length_L0, L), (state.gamma_dyn_pps, gd),
                              (state.gamma_stat_pps, gs)):
            np.copyto(target, value, where=where)
        return
    state.tension_FU.T[...] = T
    state.polar_velocity_L0_s.T[...] = v
    state.velocity_root.T[...] = u
    state.activation.T[...] = f
    state.length_L0[...] = L
    state.gamma_dyn_pps[...] = gd
    state.gamma_stat_pps[...] = gs


def advance(state: SpindleState, L1, gd1, gs1, h, theta: float, c: FibreColumns):
    """One theta-method step from the state to (L1, gd1, gs1), unchecked.

    ``h`` is the step (s), a float or an (n,) array of one per spindle (arms sampled at their
    own times).

    Returns (T1, v1, u1, f1), each (3, n). Nothing in ``state`` is modified: the caller
    commits the result once it is known to be finite, so a failed step leaves the state as it
    was. For the implicit settings the returned arrays may be buffers that the state's
    workspace reuses: they are valid until the next ``advance`` of the same state (``commit``
    copies them into the state, :func:`afferents_from_tension` reads them).
    """
    if theta == 0.0:
        return plain_advance(state, L1, gd1, gs1, h, theta, c)
    if np.ndim(h):  # a step size per spindle: in numpy blocks, whatever n
        return advance_batched(state, L1, gd1, gs1, spindle_step_constants(c, h, theta))
    # Two faster implementations of the implicit step pay for themselves (CPU per step,
    # trapezoidal at 1 ms, `bench_spindle.py --paths`, 2026-12-01): on floats up to SMALL_N
    # spindles, 13x the plain step at n = 1, 7x at 2, 3.4x at 8 (and 1.6x the batched step
    # at 8); in numpy blocks beyond, 2.9x the plain step at n = 64, 5x at 4096, 7.6x at 65536.
    k = step_constants(c, h, theta)
    if state.n <= SMALL_N:
        return advance_small(state, L1, gd1, gs1, k)
    return advance_batched(state, L1, gd1, gs1, k)


def plain_advance(state: SpindleState, L1, gd1, gs1, h: float, theta: float, c: FibreColumns):
    """One theta-method step written plainly from the model equations; (T1, v1, z1, f1),
    each (3, n), as :func:`advance` returns them (``state`` is not modified).

    Over the step, dT/dt = KSR*(dL - v) is integrated exactly for its dL part, and M dv/dt =
    F (see :func:`force`) and df/dt = (a - f)/tau with the theta-method. For theta > 0 the
    unknown is z = sgn(v)|v|^(a/3) (see the module docstring): Newton on the step residual
    M*(v1 - v0)/h - (1 - theta)*F0 - theta*F1 with its analytic slope, from the previous z,
    steps capped at 0.25, to |dz| <= PLAIN_NEWTON_TOL_Z.
    """
    T0, v0, z0, f0 = (a.T for a in (state.tension_FU, state.polar_velocity_L0_s,
                                     state.velocity_root, state.activation))
    L0 = state.length_L0
    gd1, gs1 = (np.broadcast_to(x, (state.n,)) for x in (gd1, gs1))
    a0 = activation_target(_drive_rows(state.gamma_dyn_pps, state.gamma_stat_pps), c.freq, c.p)
    a1 = activation_target(_drive_rows(gd1, gs1), c.freq, c.p)
    rate = h / c.tau_safe
    f1 = (f0 + rate * ((1 - theta) * (a0 - f0) + theta * a1)) / (1 + theta * rate)
    f1 = np.where(c.lagged[:, None], f1, a1)
    F0 = force(T0, z0, L0, f0, c)
    A = T0 + c.KSR * (L1 - L0) - (1 - theta) * h * c.KSR * v0
    if theta == 0.0:
        v1 = v0 + (h / c.M) * F0
        z1 = _z_from_velocity(v1, c)
    else:
        z1 = _plain_newton(z0.copy(), A, F0, v0, L1, f1, h, theta, c)
        v1 = _velocity_from_z(z1, c)
    T1 = A - theta * h * c.KSR * v1
    check_finite(T1, v1, h)
    return T1, v1, z1, f1


def _plain_newton(z, A, F0, v0, L1, f1, h, theta, c):
    """The new z of :func:`plain_advance` (T1 = A - theta*h*KSR*v1), in place in ``z``."""
    C_beta = c.beta0 + c.beta_drive * f1
    with np.errstate(invalid="ignore"):
        for _ in range(PLAIN_NEWTON_MAX_ITER):
            v = _velocity_from_z(z, c)
            dv_dz = (3.0 / c.a) * np.abs(z) ** (3.0 / c.a - 1.0)
            T1 = A - theta * h * c.KSR * v
            residual = c.M * (v - v0) / h - (1 - theta) * F0 - theta * force(T1, z, L1, f1, c)
            # d/dz of theta*F1: T1 moves with v, the polar length with -T1/KSR
            dT_dz = -theta * h * c.KSR * dv_dz
            damping = np.where(z > 0, c.CL, c.CS) * C_beta
            beyond_R = L1 - c.LSR0 - T1 / c.KSR - c.R
            dF_dz = (dT_dz * (c.k1 + damping * z**3 / c.KSR * (beyond_R > 0))
                     - 3 * damping * z**2 * np.maximum(beyond_R, 0.0))
            slope = c.M / h * dv_dz - theta * dF_dz
            dz = np.clip(residual / np.maximum(slope, 1e-300), -0.25, 0.25)
            z -= dz
            if np.abs(dz).max() <= PLAIN_NEWTON_TOL_Z:
                return z
    raise FloatingPointError(
        f"the plain implicit step did not converge in {PLAIN_NEWTON_MAX_ITER} iterations; "
        "state left unchanged")
