"""A tight-tolerance stiff reference solution of the spindle model (needs scipy).

Independent of the code it checks: it imports nothing from :mod:`spindle`. It restates the
model from the published equations (``../shared/spec/mileusnic2006.md``, Mileusnic et al. 2006)
with its own copy of Table 1 (:data:`TABLE_1`, transcribed from the paper's table, the human
preset its gains x 1/5 as in the seed paper), its own right-hand side and its own afferent-rate
function. It integrates the published second-order form -- state (T, dT/dt) per fibre plus the
bag1 and bag2 activations, with the M * d2L/dt2 input term -- with scipy's Radau method at
rtol = 1e-10, where :mod:`spindle.core` uses the (T, v) form and a theta-method. The modelling
choices the spec leaves open are taken as the code documents them: the polar-region velocity v
picks CL or CS, and each fibre's potential is clipped at 0 before the endings combine.

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

import dataclasses
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

# -- the published constants ------------------------------------------------------------------

TABLE_1: dict[str, tuple[float | None, float | None, float | None]] = {
    # Mileusnic et al. (2006) Table 1, cat, as (bag1, bag2, chain); None where the table has
    # "-" (the fibre has no such term). Units: FU, L0, s, pps as in the spec's table.
    "KSR": (10.4649, 10.4649, 10.4649),
    "KPR": (0.15, 0.15, 0.15),
    "M": (0.0002, 0.0002, 0.0002),
    "beta0": (0.0605, 0.0822, 0.0822),
    "beta1": (0.2592, None, None),
    "beta2": (None, -0.046, -0.069),
    "Gamma1": (0.0289, None, None),
    "Gamma2": (None, 0.0636, 0.0954),
    "CL": (1.0, 1.0, 1.0),
    "CS": (0.42, 0.42, 0.42),
    "R": (0.46, 0.46, 0.46),
    "a": (0.3, 0.3, 0.3),
    "LSR0": (0.04, 0.04, 0.04),
    "LPR0": (0.76, 0.76, 0.76),
    "LNSR": (0.0423, 0.0423, 0.0423),
    "LNPR": (None, 0.89, 0.89),
    "X": (None, 0.7, 0.7),
    "Lsec": (None, 0.04, 0.04),
    "G_primary": (20000.0, 10000.0, 10000.0),
    "G_secondary": (None, 7250.0, 7250.0),
    "freq": (60.0, 60.0, 90.0),
    "p": (2.0, 2.0, 2.0),
    "tau": (0.149, 0.205, None),  # chain: no lag (its activation is its target)
}
S_OCCLUSION = 0.156
"""Partial occlusion factor S of the primary ending (Table 1)."""
HUMAN_GAIN_SCALE = 1 / 5
"""The seed paper's human spindle: every afferent gain G of Table 1 x 1/5, all else as cat."""


@dataclass(frozen=True)
class Fibre:
    """One fibre's constants, named as in the paper. ``beta_drive`` and ``Gamma_drive`` are
    beta1 / Gamma1 (bag1, driven by gamma_dyn) or beta2 / Gamma2 (bag2, chain: gamma_stat);
    ``tau = 0`` means no activation lag; a fibre without a secondary ending has
    ``G_secondary = 0`` (its LNPR, X, Lsec are then unused)."""

    KSR: float
    KPR: float
    M: float
    beta0: float
    beta_drive: float
    Gamma_drive: float
    CL: float
    CS: float
    R: float
    a: float
    LSR0: float
    LPR0: float
    LNSR: float
    LNPR: float
    X: float
    Lsec: float
    G_primary: float
    G_secondary: float
    freq: float
    p: float
    tau: float


@dataclass(frozen=True)
class ReferenceParams:
    """The three fibres (bag1, bag2, chain) and the occlusion factor S."""

    fibres: tuple[Fibre, Fibre, Fibre]
    S: float

    def scale_gains(self, factor: float) -> ReferenceParams:
        return ReferenceParams(tuple(dataclasses.replace(
            f, G_primary=f.G_primary * factor, G_secondary=f.G_secondary * factor)
            for f in self.fibres), self.S)


def _fibre_from_table(i: int) -> Fibre:
    row = {name: values[i] for name, values in TABLE_1.items()}
    drive = "1" if i == 0 else "2"

    def value(name: str) -> float:
        return 0.0 if row[name] is None else row[name]

    return Fibre(
        KSR=row["KSR"], KPR=row["KPR"], M=row["M"], beta0=row["beta0"],
        beta_drive=row["beta" + drive], Gamma_drive=row["Gamma" + drive],
        CL=row["CL"], CS=row["CS"], R=row["R"], a=row["a"], LSR0=row["LSR0"],
        LPR0=row["LPR0"], LNSR=row["LNSR"], LNPR=value("LNPR"), X=value("X"),
        Lsec=value("Lsec"), G_primary=row["G_primary"], G_secondary=value("G_secondary"),
        freq=row["freq"], p=row["p"], tau=value("tau"),
    )


PUBLISHED_CAT = ReferenceParams(tuple(_fibre_from_table(i) for i in range(3)), S_OCCLUSION)
"""Cat spindle, Table 1 as published."""
PUBLISHED_HUMAN = PUBLISHED_CAT.scale_gains(HUMAN_GAIN_SCALE)
"""Human spindle of the seed paper."""

_CODE_NAMES = {  # the code's parameter names (spindle.params.FibreParams), for conversion
    "KSR": "KSR_FU_L0", "KPR": "KPR_FU_L0", "M": "M_FU_s2_L0", "beta0": "beta0_FU_s_L0",
    "beta_drive": "beta_drive_FU_s_L0", "Gamma_drive": "Gamma_drive_FU", "CL": "CL",
    "CS": "CS", "R": "R_L0", "a": "a", "LSR0": "LSR0_L0", "LPR0": "LPR0_L0", "LNSR": "LNSR_L0",
    "LNPR": "LNPR_L0", "X": "X", "Lsec": "Lsec_L0", "G_primary": "G_primary_pps_L0",
    "G_secondary": "G_secondary_pps_L0", "freq": "freq_pps", "p": "p", "tau": "tau_s",
}


def as_reference_params(params) -> ReferenceParams:
    """``params`` as :class:`ReferenceParams`. A :class:`spindle.SpindleParams` (a custom model
    of the code's) is read attribute by attribute; checks that use the published values pass
    :data:`PUBLISHED_CAT` / :data:`PUBLISHED_HUMAN`, which do not come from the code."""
    if isinstance(params, ReferenceParams):
        return params
    try:
        fibres = tuple(Fibre(**{ours: float(getattr(f, theirs))
                                for ours, theirs in _CODE_NAMES.items()})
                       for f in params.fibres)
        return ReferenceParams(fibres, float(params.S))
    except AttributeError as exc:
        raise TypeError(f"params={params!r} is neither ReferenceParams nor SpindleParams") \
            from exc


def afferent_rates(tension_FU: np.ndarray, length_L0, params: ReferenceParams = PUBLISHED_CAT
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Ia and II (pps), each (n,), of fibre tensions (n, 3) at fascicle lengths (n,).

    The spec's section 4-5: stretch of the sensory region beyond threshold s = T/KSR - (LNSR -
    LSR0); primary G_pri s; secondary G_sec [X (Lsec/LSR0) s + (1 - X)(Lsec/LPR0)(L - T/KSR -
    LSR0 - LNPR)]; each fibre's potential clipped at 0; Ia = max(A, B) + S min(A, B) with A the
    bag1 primary and B the bag2 + chain primaries; II the sum of the secondaries."""
    T = np.atleast_2d(np.asarray(tension_FU, dtype=float))
    L = np.broadcast_to(np.asarray(length_L0, dtype=float), T.shape[:1])
    primary, secondary = [], []
    for i, f in enumerate(params.fibres):
        sensory_L0 = T[:, i] / f.KSR
        s = sensory_L0 - (f.LNSR - f.LSR0)
        primary.append(np.maximum(f.G_primary * s, 0.0))
        polar_beyond_L0 = L - sensory_L0 - f.LSR0 - f.LNPR
        secondary.append(np.maximum(f.G_secondary * (
            f.X * (f.Lsec / f.LSR0) * s + (1 - f.X) * (f.Lsec / f.LPR0) * polar_beyond_L0), 0.0))
    A, B = primary[0], primary[1] + primary[2]
    ia = np.maximum(np.maximum(A, B) + params.S * np.minimum(A, B), 0.0)
    ii = np.maximum(secondary[1] + secondary[2], 0.0)
    return ia, ii


# -- the stimulus and the solver --------------------------------------------------------------

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
    params=PUBLISHED_CAT,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    eps_L0_s: float = 1e-7,
) -> ReferenceSolution:
    """Ia and II (pps) of one spindle at ``t_eval_s``, from a stiff solver at tight tolerance.

    The spindle starts at rest at the stimulus' initial length and drive (polar velocity 0,
    tension in closed form). ``params``: :class:`ReferenceParams` (default: Table 1, cat) or a
    :class:`spindle.SpindleParams`, converted by :func:`as_reference_params`.
    """
    solve_ivp = _require_scipy()
    t_eval_s = _checked_eval_times(t_eval_s, stimulus.duration_s)
    params = as_reference_params(params)
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
    ia, ii = afferent_rates(T, L, params)
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

    def __init__(self, stimulus: Stimulus, params: ReferenceParams, eps_L0_s: float):
        fib = params.fibres
        drive = (stimulus.gamma_dyn_pps, stimulus.gamma_stat_pps, stimulus.gamma_stat_pps)
        self.stimulus = stimulus
        self.target = [g**f.p / (g**f.p + f.freq**f.p)
                       for g, f in zip(drive, fib, strict=True)]
        # Plain floats: the solver calls rhs ~1e5 times with 8 states, where numpy's
        # per-call overhead would dominate.
        self.consts = [
            (f.KSR, f.KPR, f.M, f.beta0, f.beta_drive, f.Gamma_drive, f.CL, f.CS, f.R, f.a,
             f.LSR0, f.LPR0)
            for f in fib
        ]
        self.tau = (fib[0].tau, fib[1].tau)
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
