"""A tight-tolerance stiff reference solution of the spindle model (needs scipy).

It integrates the model in its published second-order form -- state (T, dT/dt) per fibre plus
the bag1 and bag2 activations, with the M * d2L/dt2 input term -- with scipy's Radau method at
rtol = 1e-10, independently of the (T, v) form and theta-method of :mod:`spindle.core`.

The one change to the equations: sgn(v)|v|^a, whose slope is infinite at v = 0, is replaced by
v * (v^2 + eps^2)^((a-1)/2) with eps = 1e-7 L0/s by default. Its effect on the rates falls as
eps^2 (x100 per decade): on four 3.3 s Fig. 3 runs (onsets 1.0-1.0053 s, gamma_dyn up to 300
pps) eps = 1e-7 differs from eps = 1e-9 by at most 7e-6 pps (1e-6: 7e-4, 1e-5: 0.06 pps), far
below the 0.32 pps worst-run error of the trapezoidal rule at 1 ms and the ~3e-3 pps it reaches
at 0.1 ms. The stimulus is integrated piecewise between its breakpoints (ramp corners); at
each one dT/dt jumps by KSR times the jump in dL/dt, the integral of the M * d2L/dt2 impulse.

Within a segment [t0, t1] the stimulus' velocity and acceleration are read strictly inside it
(at t clamped to [t0 + d, t1 - d], d = 1e-12 s x max(1, t)), i.e. as the segment's one-sided
limits at its ends. Radau's last stage sits exactly on t1, where a piecewise velocity such as
``v if on <= t < off else 0`` already takes the next piece's value. Read there, the last stage
of a rest hold saw the ramp's full speed; depending on the step that reached t1 (so on the
hold's length) the step was then rejected again and again until it fell below the float
spacing ("Required step size is less than spacing between numbers"), whatever eps.

scipy is imported only when a reference solution is asked for (extra ``reference``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from spindle.core import afferents_from_tension, columns
from spindle.params import CAT, SpindleParams


@dataclass(frozen=True)
class Stimulus:
    """A fascicle-length trajectory in continuous time with its fusimotor drive.

    Attributes:
        length_L0, velocity_L0_s, acceleration_L0_s2: callables of time (s) -> float.
        duration_s: end time; the trajectory starts at t = 0.
        breakpoints_s: times where velocity or acceleration jump (integration restarts there).
            At a breakpoint the callables may return either one-sided value: each segment
            reads them strictly inside itself.
        gamma_dyn_pps, gamma_stat_pps: drive held constant over the whole run.
    """

    length_L0: Callable[[float], float]
    velocity_L0_s: Callable[[float], float]
    acceleration_L0_s2: Callable[[float], float]
    duration_s: float
    breakpoints_s: Sequence[float] = field(default_factory=tuple)
    gamma_dyn_pps: float = 0.0
    gamma_stat_pps: float = 0.0


def _require_scipy():
    try:
        from scipy.integrate import solve_ivp
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError(
            "the reference solver needs scipy: pip install 'proprio-elbow[reference]'"
        ) from exc
    return solve_ivp


@dataclass(frozen=True)
class ReferenceSolution:
    t_s: np.ndarray
    ia: np.ndarray
    ii: np.ndarray
    tension_FU: np.ndarray  # (T, 3)
    n_rhs_evaluations: int


def solve_reference(
    stimulus: Stimulus,
    t_eval_s: np.ndarray,
    params: SpindleParams = CAT,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    eps_L0_s: float = 1e-7,
) -> ReferenceSolution:
    """Ia and II (pps) of one spindle at ``t_eval_s``, from a stiff solver at tight tolerance.

    The spindle starts at rest at the stimulus' initial length and drive (as
    :func:`spindle.core.equilibrium_state` does).
    """
    solve_ivp = _require_scipy()
    t_eval_s = _checked_eval_times(t_eval_s, stimulus.duration_s)
    model = _SecondOrderModel(stimulus, params, eps_L0_s)
    y = model.rest_state()
    edges = sorted({0.0, stimulus.duration_s, *(b for b in stimulus.breakpoints_s
                                                if 0 < b < stimulus.duration_s)})
    ts, Ts = [], []
    nfev = 0
    for t0, t1 in itertools.pairwise(edges):
        if t0 > 0:
            y = model.across_breakpoint(y, t0)
        # The segment's inputs are its one-sided limits at t0 and t1 (see the module docstring).
        inside = (t0 + min(_one_side_s(t0), (t1 - t0) / 4),
                  t1 - min(_one_side_s(t1), (t1 - t0) / 4))
        mask = (t_eval_s >= t0) & ((t1 == edges[-1]) | (t_eval_s < t1))
        # t1 is appended so that the segment's end state is exact for the next restart.
        t_seg = np.append(np.minimum(t_eval_s[mask], t1), t1)
        t_seg = t_seg[np.r_[np.diff(t_seg) > 0, True]]
        sol = solve_ivp(model.rhs, (t0, t1), y, method="Radau", rtol=rtol, atol=atol,
                        t_eval=t_seg, jac=model.jac, args=inside)
        if not sol.success:
            raise RuntimeError(f"reference solver failed on [{t0}, {t1}] s: {sol.message}")
        nfev += sol.nfev
        ts.append(t_eval_s[mask])
        Ts.append(_repeat_last(sol.y[0:3].T, int(mask.sum())))
        y = sol.y[:, -1]
    t = np.concatenate(ts)
    T = np.concatenate(Ts)
    L = np.array([stimulus.length_L0(ti) for ti in t])
    ia, ii = afferents_from_tension(np.ascontiguousarray(T.T), L, columns(params))
    return ReferenceSolution(t, ia, ii, T, nfev)


def _checked_eval_times(t_eval_s, duration_s: float) -> np.ndarray:
    t_eval_s = np.asarray(t_eval_s, dtype=float)
    if t_eval_s.ndim != 1 or t_eval_s.size == 0:
        raise ValueError(f"t_eval_s must be a non-empty 1-D array, got shape {t_eval_s.shape}")
    if t_eval_s.min() < 0 or t_eval_s.max() > duration_s * (1 + 1e-12):
        raise ValueError(
            f"t_eval_s spans [{t_eval_s.min()}, {t_eval_s.max()}] s, outside the stimulus' "
            f"[0, {duration_s}] s"
        )
    return t_eval_s


class _SecondOrderModel:
    """The published second-order form: y = (T of each fibre, dT/dt of each fibre, bag1 and
    bag2 activation); the chain fibre's activation sits at its target."""

    def __init__(self, stimulus: Stimulus, params: SpindleParams, eps_L0_s: float):
        fib = params.fibres
        drive = (stimulus.gamma_dyn_pps, stimulus.gamma_stat_pps, stimulus.gamma_stat_pps)
        self.stimulus = stimulus
        self.target = [g**f.p / (g**f.p + f.freq_pps**f.p)
                       for g, f in zip(drive, fib, strict=True)]
        # Plain floats: the solver calls rhs ~1e5 times with 8 states, where numpy's
        # per-call overhead would dominate.
        self.consts = [
            (f.KSR_FU_L0, f.KPR_FU_L0, f.M_FU_s2_L0, f.beta0_FU_s_L0, f.beta_drive_FU_s_L0,
             f.Gamma_drive_FU, f.CL, f.CS, f.R_L0, f.a, f.LSR0_L0, f.LPR0_L0)
            for f in fib
        ]
        self.tau = (fib[0].tau_s, fib[1].tau_s)
        self.eps2 = eps_L0_s * eps_L0_s

    def rest_state(self) -> np.ndarray:
        """Equilibrium at rest at the stimulus' start: v = 0, so dT/dt = KSR * dL."""
        L_start = self.stimulus.length_L0(0.0)
        dL_start = self.stimulus.velocity_L0_s(0.0)
        return np.array(
            [(c[5] * ft + c[1] * (L_start - c[10] - c[11])) / (1 + c[1] / c[0])
             for c, ft in zip(self.consts, self.target, strict=True)]
            + [c[0] * dL_start for c in self.consts] + self.target[:2]
        )

    def across_breakpoint(self, y: np.ndarray, t0: float) -> np.ndarray:
        """dT/dt jumps with dL/dt at a breakpoint (v, the polar velocity, is continuous)."""
        velocity = self.stimulus.velocity_L0_s
        jump = velocity(t0 + _one_side_s(t0)) - velocity(t0 - _one_side_s(t0))
        y = y.copy()
        y[3:6] += np.array([c[0] for c in self.consts]) * jump
        return y

    def rhs(self, t, y, t_lo, t_hi):
        stimulus, eps2 = self.stimulus, self.eps2
        L = stimulus.length_L0(t)
        t_in = min(max(t, t_lo), t_hi)
        dL = stimulus.velocity_L0_s(t_in)
        ddL = stimulus.acceleration_L0_s2(t_in)
        f = (y[6], y[7], self.target[2])
        out = np.empty(8)
        for i, (KSR, KPR, M, b0, bd, Gd, CL, CS, R, a, LSR0, LPR0) in enumerate(self.consts):
            T, Td = y[i], y[3 + i]
            v = dL - Td / KSR
            damp = (CL if v > 0 else CS) * (b0 + bd * f[i]) * v * (v * v + eps2) ** ((a - 1) / 2)
            polar = L - LSR0 - T / KSR
            out[i] = Td
            out[3 + i] = (KSR / M) * (damp * (polar - R) + KPR * (polar - LPR0) + M * ddL
                                      + Gd * f[i] - T)
        out[6] = (self.target[0] - y[6]) / self.tau[0]
        out[7] = (self.target[1] - y[7]) / self.tau[1]
        return out

    def jac(self, t, y, t_lo, t_hi):
        L = self.stimulus.length_L0(t)
        dL = self.stimulus.velocity_L0_s(min(max(t, t_lo), t_hi))
        f = (y[6], y[7], self.target[2])
        J = np.zeros((8, 8))
        for i, (KSR, KPR, M, b0, bd, Gd, CL, CS, R, a, LSR0, _LPR0) in enumerate(self.consts):
            T, Td = y[i], y[3 + i]
            v = dL - Td / KSR
            C = CL if v > 0 else CS
            s2 = v * v + self.eps2
            shape = v * s2 ** ((a - 1) / 2)
            damp = C * (b0 + bd * f[i]) * shape
            d_shape_dv = s2 ** ((a - 3) / 2) * (self.eps2 + a * v * v)
            polar = L - LSR0 - T / KSR
            k = KSR / M
            J[i, 3 + i] = 1.0
            J[3 + i, i] = k * (-(damp + KPR) / KSR - 1.0)
            J[3 + i, 3 + i] = k * C * (b0 + bd * f[i]) * d_shape_dv * (-1.0 / KSR) * (polar - R)
            if i < 2:
                J[3 + i, 6 + i] = k * (C * bd * shape * (polar - R) + Gd)
        J[6, 6] = -1.0 / self.tau[0]
        J[7, 7] = -1.0 / self.tau[1]
        return J


def _one_side_s(t_s: float) -> float:
    """How far from a breakpoint at t_s the stimulus is read to get a one-sided value: ~2000
    float spacings at 3 s, so rounding in the stimulus' own comparison cannot put it on the
    wrong side, and small enough that a smooth input moves by a negligible amount."""
    return 1e-12 * max(1.0, abs(t_s))


def _repeat_last(rows: np.ndarray, n: int) -> np.ndarray:
    """The first n solver rows; rows past the end (t_eval points that rounded onto the end
    time t1) repeat the last one."""
    if n <= rows.shape[0]:
        return rows[:n]
    return np.vstack((rows, np.repeat(rows[-1:], n - rows.shape[0], axis=0)))


def ramp_and_hold(
    start_L0: float = 0.95,
    end_L0: float = 1.08,
    speed_L0_s: float = 0.66,
    ramp_start_s: float = 1.0,
    duration_s: float = 3.3,
    gamma_dyn_pps: float = 0.0,
    gamma_stat_pps: float = 0.0,
) -> Stimulus:
    """The Mileusnic et al. (2006) Fig. 3 stimulus: hold, ramp at ``speed_L0_s``, hold."""
    if speed_L0_s <= 0:
        raise ValueError(f"speed_L0_s={speed_L0_s!r} must be > 0")
    ramp_end_s = ramp_start_s + (end_L0 - start_L0) / speed_L0_s
    if not 0 <= ramp_start_s < ramp_end_s <= duration_s:
        raise ValueError(
            f"the ramp [{ramp_start_s}, {ramp_end_s}] s must fit in [0, {duration_s}] s"
        )
    slope = (end_L0 - start_L0) / (ramp_end_s - ramp_start_s)

    def length(t: float) -> float:
        return start_L0 + slope * min(max(t - ramp_start_s, 0.0), ramp_end_s - ramp_start_s)

    def velocity(t: float) -> float:
        return slope if ramp_start_s <= t < ramp_end_s else 0.0

    return Stimulus(length, velocity, lambda t: 0.0, duration_s, (ramp_start_s, ramp_end_s),
                    gamma_dyn_pps, gamma_stat_pps)
