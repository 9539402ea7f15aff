"""The Golgi tendon organ (Ib) step: Lin & Crago (2002), its linear part integrated exactly.

The model (constants in :mod:`spindle.tendon_organ_params`) is a log stage r(F) followed by
a linear system, the low-pass 1/(tau s + 1) in cascade with H(s). Written in state space with
no derivative of the input anywhere (H is split into its direct term b2 and a strictly
proper remainder (c1 s + c0)/(s^2 + a1 s + a0), c1 = b1 - b2 a1, c0 = b0 - b2 a0):

    dx/dt  = (r - x) / tau                      the low-pass
    dw1/dt = w2                                 the remainder in controllable form
    dw2/dt = x - a0 w1 - a1 w2
    y = b2 x + c0 w1 + c1 w2,   Ib = max(0, y)

The state is z = (x, w1, w2); dz/dt = A z + B r. Over a step of h the force is the straight
line between its values at the step's ends (as the spindle's sub-steps take the length
between samples, without the Hermite curvature), and r(t) = G1 ln(F(t)/G2 + 1) of that line
enters through the line alpha + beta s/h with the same mean and first moment over the step,
computed by Simpson's rule from r0, r1 and r at the mid-force r_mid:

    beta = r1 - r0,   alpha = r0 + delta,   delta = (2/3) (r_mid - (r0 + r1)/2)

and, since r_mid - (r0 + r1)/2 = (G1/2) ln((u0 + u1)^2 / (4 u0 u1)) for u = 1 + F/G2 and
(u0 + u1)^2 / (4 u0 u1) = cosh^2(d) with d = (r1 - r0) / (2 G1),

    delta = (2 G1 / 3) ln cosh(d)

from the two logs the step has anyway: no division, no cancellation, and for
|d| < :data:`SERIES_D` (every step but a jump) three terms of its series.

The step is the exact solution of the linear system for that line:

    z1 = Phi z0 + G0 alpha + G1 beta

with Phi = e^{Ah}, G0 = int_0^h e^{As} ds B and G1 = int_0^h e^{A(h-s)} (s/h) ds B, read off
one matrix exponential of the augmented 5 x 5 system (:func:`plan`; a Taylor series with
scaling and squaring, numpy only). So the step is stable for every h; its error is what the
projection of the log onto a line leaves, O(h^4) for a force linear over the step (delta is
the log's curvature: a plain first-order hold in r, delta = 0, is 0.29 pps RMS off on a
20 ms force rise sampled at 10 ms, this 0.008), and the force's own departure from a line
between samples. No force is differentiated.

Inputs and their rules (checked before anything changes; a call that raises leaves the state
as it was):
- force (N): NaN or infinite -> ValueError; above :data:`MAX_FORCE_N` -> ValueError; negative
  -> taken as 0 (a tendon cannot push: the slack tendon carries no force), at the samples,
  before the line between them is drawn; the count of such values is the caller's to keep
  (:func:`count_negative`);
- force scale G2 (N): finite and at least :data:`MIN_FORCE_SCALE_N` (1e-6 N), a scalar or
  one per muscle;
- step h (s): finite, > 0 and <= :data:`MAX_STEP_S` -> else ValueError.
Rates are never negative (the max(0, y) of the model) and never non-finite (bounded inputs
into a stable linear system).

Shapes: a leading axis of muscles, (n,) per input and output; z is kept as a (3, n) array.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from spindle.backends import DEFAULT_BACKEND, implementation
from spindle.tendon_organ_params import (
    HUMAN,
    MAX_FORCE_N,
    MAX_STEP_S,
    MIN_FORCE_SCALE_N,
    TendonOrganParams,
    check_force_scales,
    check_step,
)

__all__ = [
    "MAX_FORCE_N",
    "MAX_STEP_S",
    "MIN_FORCE_SCALE_N",
    "SERIES_D",
    "TendonOrganPlan",
    "TendonOrganState",
    "TendonOrgans",
    "check_force_scales",
    "check_step",
    "count_negative",
    "equilibrium_state",
    "ln_cosh",
    "log_stage",
    "make_tendon_organs",
    "plan",
    "plan_steps",
    "rate_pps",
    "simulate",
    "state_space",
    "step",
]


def state_space(params: TendonOrganParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A (3, 3), B (3,), C (3,)) of the linear part: dz/dt = A z + B r, y = C z."""
    b2, b1, b0 = params.num
    a1, a0 = params.den
    k = 1.0 / params.tau_lowpass_s
    A = np.array([[-k, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, -a0, -a1]])
    B = np.array([k, 0.0, 0.0])
    C = np.array([b2, b0 - b2 * a0, b1 - b2 * a1])
    return A, B, C


TAYLOR_TERMS = 20
"""Terms of the exponential's series after scaling to norm <= 1/2: the remainder is below
0.5^21 / 21! ~ 1e-26, far under double rounding."""


def expm_taylor(M: np.ndarray) -> np.ndarray:
    """e^M of a small square matrix, or of each of a stack (..., m, m): scaled by 2^-s to
    1-norm <= 1/2 (s per matrix), a Taylor series, s squarings. (``ps_gto_plan_init`` in C
    runs the same steps in the same order.)"""
    M = np.asarray(M, dtype=np.float64)
    m = M.shape[-1]
    stack = M.reshape(-1, m, m)
    norm = np.max(np.sum(np.abs(stack), axis=1), axis=1)
    s = np.zeros(norm.shape, dtype=np.int64)
    while (norm > 0.5).any():
        big = norm > 0.5
        norm = np.where(big, norm * 0.5, norm)
        s += big
    X = stack / (2.0 ** s)[:, None, None]
    E = np.broadcast_to(np.eye(m), stack.shape).copy()
    term = E.copy()
    for k in range(1, TAYLOR_TERMS + 1):
        term = (term @ X) / k
        E = E + term
    for q in range(int(s.max(initial=0))):
        E = np.where((q < s)[:, None, None], E @ E, E)
    return E.reshape(M.shape)


@dataclass(frozen=True)
class TendonOrganPlan:
    """The step's constants for one (params, h): z1 = phi z0 + g0 alpha + g1 beta,
    y = c z. Made by :func:`plan`; read-only."""

    params: TendonOrganParams
    dt_s: float | np.ndarray
    phi: np.ndarray
    g0: np.ndarray
    g1: np.ndarray
    c: np.ndarray


def plan(params: TendonOrganParams = HUMAN, dt_s: float = 1e-3) -> TendonOrganPlan:
    """The exact step's constants for ``params`` at step ``dt_s`` (cached per pair)."""
    return _plan(params, check_step(dt_s))


@lru_cache(maxsize=64)
def _plan(params: TendonOrganParams, h: float) -> TendonOrganPlan:
    phi, g0, g1, c = _plan_arrays(params, np.array([h]))
    arrays = [phi[0], g0[0], g1[0], c]
    for a in arrays:
        a.setflags(write=False)
    return TendonOrganPlan(params, h, *arrays)


def _plan_arrays(params: TendonOrganParams, h: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(phi (m, 3, 3), g0 (m, 3), g1 (m, 3), c (3,)) of the exact step for each of m steps
    ``h`` (s): one matrix exponential of the augmented 5 x 5 system per step."""
    A, B, C = state_space(params)
    M = np.zeros((h.shape[0], 5, 5))
    M[:, :3, :3] = A * h[:, None, None]
    M[:, :3, 3] = B * h[:, None]
    M[:, 3, 4] = 1.0
    E = expm_taylor(M)
    return E[:, :3, :3].copy(), E[:, :3, 3].copy(), E[:, :3, 4].copy(), C


def plan_steps(params: TendonOrganParams, dt_s: np.ndarray) -> TendonOrganPlan:
    """The exact step's constants for n organs, each its own step ``dt_s`` (n,) (s, every
    one within :func:`check_step`'s limits; not cached): a plan whose ``phi`` is (n, 3, 3),
    ``g0`` and ``g1`` (n, 3), which :func:`step` takes as one step per organ. Organs
    sharing one step get the cached :func:`plan` instead."""
    h = np.asarray(dt_s, dtype=np.float64)
    if h.ndim != 1 or not bool(np.all((h > 0) & (h <= MAX_STEP_S))):
        raise ValueError(f"dt_s={dt_s!r} must be a 1-D array of steps in (0, {MAX_STEP_S}] s")
    if bool((h == h[0]).all()):
        return plan(params, float(h[0]))
    steps, which = np.unique(h, return_inverse=True)  # one exponential per distinct step
    phi, g0, g1, c = _plan_arrays(params, steps)
    return TendonOrganPlan(params, h, phi[which], g0[which], g1[which], c)


@dataclass
class TendonOrganState:
    """State of n tendon organs: z (3, n) = (x, w1, w2); force_N (n,), the rectified force at
    the state's time, and r_pps (n,), the log stage's value there (the start of the next
    step's line)."""

    z: np.ndarray
    force_N: np.ndarray
    r_pps: np.ndarray

    @property
    def n(self) -> int:
        return self.r_pps.shape[0]

    def copy(self) -> TendonOrganState:
        return TendonOrganState(self.z.copy(), self.force_N.copy(), self.r_pps.copy())


def _forces(force_N: object, n: int | None) -> np.ndarray:
    f = np.asarray(force_N, dtype=np.float64)
    if f.ndim > 1 or (n is not None and f.ndim == 1 and f.shape[0] != n):
        raise ValueError(f"force_N has shape {f.shape}; expected a scalar or ({n},)")
    m = n if n is not None else (f.size if f.ndim == 1 else 1)
    if f.shape != (m,):  # a scalar (broadcast_to costs as much as a pass over 4096 values)
        f = np.broadcast_to(f, (m,))
    if f.size == 0 or (f.min() > -np.inf and f.max() <= MAX_FORCE_N):  # NaN fails both
        return f
    bad = ~np.isfinite(f)
    if bad.any():
        raise ValueError(f"force_N={f[bad][0]!r} is not finite (muscle {int(np.argmax(bad))})")
    big = f > MAX_FORCE_N
    if big.any():
        raise ValueError(f"force_N={f[big][0]!r} exceeds MAX_FORCE_N={MAX_FORCE_N} N "
                         f"(muscle {int(np.argmax(big))})")
    return f


def _scales(force_scale_N: object, n: int) -> np.ndarray:
    return check_force_scales(force_scale_N, n)


def count_negative(force_N: object) -> int:
    """How many forces the step takes as 0 (negative, i.e. a slack tendon)."""
    return int(np.count_nonzero(np.asarray(force_N, dtype=np.float64) < 0))


def log_stage(force_N: object, force_scale_N: object, params: TendonOrganParams = HUMAN
              ) -> np.ndarray:
    """r = G1 ln(F+/G2 + 1) (pps) per muscle, after the input rules of the module."""
    f = _forces(force_N, None)
    g = _scales(force_scale_N, f.shape[0])
    return params.gain_pps * np.log1p(np.maximum(f, 0.0) / g)


def equilibrium_state(force_N: object, force_scale_N: object,
                      params: TendonOrganParams = HUMAN, n: int | None = None
                      ) -> TendonOrganState:
    """At rest at a constant force: x = r, w1 = r / a0, w2 = 0 (so Ib = dc_gain * r)."""
    f = _forces(force_N, n)
    r = log_stage(f, _scales(force_scale_N, f.shape[0]), params)
    z = np.stack([r, r / params.den[1], np.zeros_like(r)])
    return TendonOrganState(z, np.maximum(f, 0.0), r.copy())


def rate_pps(state: TendonOrganState, c: np.ndarray) -> np.ndarray:
    """Ib (pps) of a state: max(0, C z)."""
    return np.maximum(c @ state.z, 0.0)


SERIES_D = 0.03
"""Below this |d|, ln cosh d is d^2 (1/2 - d^2 (1/12 - d^2/45)): the next term, 17 d^8/2520,
is under 1e-11 of the sum."""


def ln_cosh(d: np.ndarray) -> np.ndarray:
    """ln cosh d by the rule of :data:`SERIES_D` (``gto_ln_cosh`` in C); beyond it
    |d| + ln(1 + e^{-2|d|}) - ln 2, which cannot overflow."""
    d = np.asarray(d, dtype=np.float64)
    d2 = d * d
    out = np.multiply(d2, 1.0 / 45.0, out=np.empty_like(d))  # d2 (1/2 - d2 (1/12 - d2/45))
    np.subtract(1.0 / 12.0, out, out=out)
    out *= d2
    np.subtract(0.5, out, out=out)
    out *= d2
    if d.size and (d.max() >= SERIES_D or d.min() <= -SERIES_D):  # a jump: logs only there
        big = np.abs(d) >= SERIES_D
        a = np.abs(d[big])
        out[big] = a + np.log1p(np.exp(-2.0 * a)) - np.log(2.0)
    return out


def step(state: TendonOrganState, force_N: object, force_scale_N: object,
         step_plan: TendonOrganPlan) -> np.ndarray:
    """Advance ``state`` in place by ``step_plan.dt_s`` to tendon force ``force_N`` (N) at the
    step's end; returns Ib (pps, (n,)) there. Inputs are checked first (module rules). A plan
    of :func:`plan_steps` with one step per organ steps each organ by its own."""
    n = state.n
    f1 = np.maximum(_forces(force_N, n), 0.0)
    g = _scales(force_scale_N, n)
    gain = step_plan.params.gain_pps
    r0 = state.r_pps
    r1 = np.divide(f1, g)  # in place from here (the same operations as the C step)
    np.log1p(r1, out=r1)
    r1 *= gain
    beta = r1 - r0
    alpha = ln_cosh(beta * (0.5 / gain))
    alpha *= 2.0 * gain / 3.0
    alpha += r0
    if step_plan.phi.ndim == 3:  # one step per organ
        z = np.einsum("nij,jn->in", step_plan.phi, state.z)
        z += step_plan.g0.T * alpha
        z += step_plan.g1.T * beta
    else:
        z = step_plan.phi @ state.z
        z += step_plan.g0[:, None] * alpha
        z += step_plan.g1[:, None] * beta
    state.z[...] = z
    state.force_N[...] = f1
    state.r_pps[...] = r1
    y = step_plan.c @ z
    return np.maximum(y, 0.0, out=y)


class TendonOrgans:
    """n tendon organs streamed in numpy: ``step(force_N) -> Ib``. The C twin is
    :class:`spindle.native.tendon_organ.CTendonOrgans`; :func:`make_tendon_organs` picks.

    Args:
        force_scale_N: G2 per muscle (N), (n,) or a scalar with ``n``.
        params: the preset; dt_s: the default step (s); force_N: the rest force to start at.
    """

    backend = "numpy"

    def __init__(self, force_scale_N: object, params: TendonOrganParams = HUMAN,
                 dt_s: float = 1e-3, force_N: object = 0.0, n: int | None = None) -> None:
        g = np.atleast_1d(np.asarray(force_scale_N, dtype=np.float64))
        n = n if n is not None else g.shape[0]
        self.params = params
        self.force_scale_N = _scales(g, n).copy()
        self.plan = plan(params, dt_s)
        self.state = equilibrium_state(force_N, self.force_scale_N, params, n)

    @property
    def n(self) -> int:
        return self.state.n

    def reset(self, force_N: object = 0.0, rows: np.ndarray | None = None) -> np.ndarray:
        """At rest at ``force_N``; returns the rates there. With ``rows`` (organ indices),
        only those organs, ``force_N`` then a scalar or one per row."""
        if rows is None:
            self.state = equilibrium_state(force_N, self.force_scale_N, self.params, self.n)
            return self.rate_pps()
        rows = np.asarray(rows, dtype=np.intp)
        fresh = equilibrium_state(force_N, self.force_scale_N[rows], self.params, rows.size)
        self.state.z[:, rows] = fresh.z
        self.state.force_N[rows] = fresh.force_N
        self.state.r_pps[rows] = fresh.r_pps
        return self.rate_pps()

    def rows_state(self, rows: np.ndarray) -> TendonOrganState:
        """A copy of the state of organs ``rows`` (for :meth:`set_rows_state`)."""
        rows = np.asarray(rows, dtype=np.intp)
        return TendonOrganState(self.state.z[:, rows].copy(), self.state.force_N[rows].copy(),
                                self.state.r_pps[rows].copy())

    def set_rows_state(self, rows: np.ndarray, saved: TendonOrganState) -> np.ndarray:
        """Organs ``rows`` back to ``saved`` (:meth:`rows_state`); returns every rate."""
        rows = np.asarray(rows, dtype=np.intp)
        self.state.z[:, rows] = saved.z
        self.state.force_N[rows] = saved.force_N
        self.state.r_pps[rows] = saved.r_pps
        return self.rate_pps()

    def run(self, force_N: np.ndarray, dt_s: float | None = None,
            first: bool = False) -> np.ndarray:
        """Steps to each row of ``force_N`` ((steps, n)); Ib after each, (steps, n), with the
        rates at the start as an extra first row if ``first`` (the C twin's ``run``). Atomic:
        every row is checked before any step."""
        p = self.plan if dt_s is None else plan(self.params, dt_s)
        f = np.asarray(force_N, dtype=np.float64).reshape(-1, self.n)
        for row in f:
            _forces(row, self.n)
        out = np.empty((f.shape[0] + int(first), self.n))
        if first:
            out[0] = self.rate_pps()
        for k in range(f.shape[0]):
            out[k + int(first)] = step(self.state, f[k], self.force_scale_N, p)
        return out

    def step(self, force_N: object, dt_s: float | None = None) -> np.ndarray:
        """One step of ``dt_s`` (default: the constructor's) to ``force_N``; Ib (pps)."""
        p = self.plan if dt_s is None else plan(self.params, dt_s)
        return step(self.state, force_N, self.force_scale_N, p)

    def rate_pps(self) -> np.ndarray:
        return rate_pps(self.state, self.plan.c)


def make_tendon_organs(force_scale_N: object, params: TendonOrganParams = HUMAN,
                       dt_s: float = 1e-3, force_N: object = 0.0,
                       backend: str = DEFAULT_BACKEND):
    """:class:`TendonOrgans` (numpy) or its C twin, by :func:`spindle.backends.resolve_backend`;
    both have ``.backend``, ``.n``, ``reset`` (all organs or some ``rows``), ``step``, ``run``
    (many steps in one call), ``rate_pps``."""
    return implementation("tendon_organs", backend)[1](force_scale_N, params, dt_s, force_N)


def simulate(force_N: object, dt_s: float, force_scale_N: object,
             params: TendonOrganParams = HUMAN, backend: str = DEFAULT_BACKEND) -> np.ndarray:
    """Ib (pps) along sampled tendon forces ``force_N`` ((T,) or (T, n), N, one sample per
    ``dt_s``), from rest at the first sample; the output has the input's shape."""
    f = np.asarray(force_N, dtype=np.float64)
    if f.ndim not in (1, 2) or f.shape[0] < 1:
        raise ValueError(f"force_N has shape {f.shape}; expected (T,) or (T, n), T >= 1")
    f2 = f.reshape(f.shape[0], -1)
    for row in f2:  # every sample checked before any is used
        _forces(row, f2.shape[1])
    organs = make_tendon_organs(force_scale_N, params, dt_s, f2[0], backend)
    if organs.n != f2.shape[1]:
        raise ValueError(f"force_scale_N gives {organs.n} muscles, force_N has {f2.shape[1]}")
    return organs.run(f2[1:], first=True).reshape(f.shape)
