"""The implicit spindle step for a few spindles, on Python floats, fibre by fibre.

The same arithmetic as :mod:`spindle.batch_step`, term by term (the two agree to rounding,
~1e-13 pps): for a few spindles numpy's per-call overhead costs more than the arithmetic.
:func:`spindle.core.advance` uses it up to :data:`SMALL_N` spindles, and
``spindle.simulate`` for one spindle (the figures are in :func:`spindle.core.advance`).
"""

from __future__ import annotations

import math

import numpy as np

from spindle.fibre_constants import (
    MAX_DRIVE_POWER,
    NEWTON_MAX_DZ,
    NEWTON_MAX_ITER,
    NEWTON_TOL_Z,
    FibreColumns,
    FibreStepConstants,
    StepConstants,
)

SMALL_N = 8
"""Up to this many spindles the step runs on Python floats, fibre by fibre."""


def as_floats(x, n: int) -> list[float]:
    """A scalar or an array broadcastable to (n,) as a list of n floats."""
    if isinstance(x, np.ndarray):
        if x.shape == (n,):
            return x.tolist()
        if x.size == 1:
            return [float(x.reshape(-1)[0])] * n
        return np.broadcast_to(x, (n,)).tolist()
    return [float(x)] * n


def advance_small(state, L1, gd1, gs1, k: StepConstants):
    """:func:`spindle.core.advance` (implicit) for a few spindles; (T1, v1, z1, f1), each
    (3, n)."""
    n = state.n
    T0 = state.tension_FU.tolist()
    v0 = state.polar_velocity_L0_s.tolist()
    z0 = state.velocity_root.tolist()
    f0 = state.activation.tolist()
    L0 = state.length_L0.tolist()
    gd0 = state.gamma_dyn_pps.tolist()
    gs0 = state.gamma_stat_pps.tolist()
    L1, gd1, gs1 = (as_floats(x, n) for x in (L1, gd1, gs1))
    out = [step_floats(k, T0[i], v0[i], z0[i], f0[i], L0[i], gd0[i], gs0[i], L1[i], gd1[i],
                       gs1[i]) for i in range(n)]
    # (n spindles) x (T, v, z, f) x 3 fibres -> four (3, n) arrays
    arr = np.array(out).transpose(1, 2, 0)
    return arr[0], arr[1], arr[2], arr[3]


def _drive_powers(gd: float, gs: float, k: StepConstants) -> list[float]:
    return [min(g * g if p == 2.0 else _float_power(g, p), MAX_DRIVE_POWER)
            for g, p in zip((gd, gs, gs), k.p, strict=True)]


def _float_power(g: float, p: float) -> float:
    try:
        return g**p
    except OverflowError:  # Python floats raise where numpy gives inf
        return math.inf


def step_floats(k: StepConstants, T0, v0, z0, f0, L0, gd0, gs0, L1, gd1, gs1):
    """One implicit step of one spindle on floats; returns the new (T, v, z, f), each a list
    over the three fibres. The arithmetic is that of the vectorised step, term by term."""
    old = k.theta < 1.0
    same_drive = gd0 == gd1 and gs0 == gs1
    power = _drive_powers(gd1, gs1, k)
    power_old = None if same_drive or not old else _drive_powers(gd0, gs0, k)
    dL = L1 - L0
    T1, v1, z1, f1 = [], [], [], []
    for i, fc in enumerate(k.fibre):
        g = power[i]
        if not k.lagged[i]:
            fn = g / (g + fc.freq_p)
        elif old and same_drive:
            fn = f0[i] * fc.keep + g / (g + fc.freq_p) * (fc.from_a0 + fc.from_a1)
        else:
            fn = _lagged_activation(f0[i], g, None if power_old is None else power_old[i], fc)
        A, p0, rhs, cM, cD = _known_terms(T0[i], v0[i], z0[i], f0[i], fn, L0, dL, fc, old)
        z = _guess(z0[i], p0, rhs, cM, cD, fc, k)
        # Where the new polar region may end up no longer than R, the damping's clip at 0 is
        # part of the equation; |v| <= |rhs| at its root (the damping has the sign of v).
        clip = p0 <= k.th_h * abs(rhs)
        if clip:
            bound = abs(rhs) ** (1.0 / fc.three_over_a)
            if not abs(z) <= bound:  # also a NaN guess (no slope at v = 0, p0 <= 0)
                z = math.copysign(bound, rhs)
        z = newton_float(z, p0, rhs, cM, cD, k, fc.three_over_a, clip)
        abs_z = abs(z)
        if k.a_is_03:
            sq = z * z
            t = sq * sq
            v = t * t * abs_z * z
        else:
            v = abs_z ** (fc.three_over_a - 1.0) * z
        T1.append(A - v * fc.th_h_KSR)
        v1.append(v)
        z1.append(z)
        f1.append(fn)
    # A sum is finite only if every term is (the values are far below overflow).
    if not math.isfinite(sum(T1) + sum(v1)):
        raise FloatingPointError(
            "the spindle step produced a non-finite tension or velocity; state left unchanged "
            f"(step {k.h!r} s)"
        )
    return T1, v1, z1, f1


def _lagged_activation(f: float, g: float, g_old: float | None,
                       fc: FibreStepConstants) -> float:
    """f1 = keep*f0 + from_a0*a0 + from_a1*a1 from the drive powers g (new), g_old (old;
    None for theta = 1)."""
    target = g / (g + fc.freq_p)
    fn = f * fc.keep
    if g_old is not None:
        fn = fn + g_old / (g_old + fc.freq_p) * fc.from_a0
    return fn + target * fc.from_a1


def _known_terms(T, v, z, f, fn, L0, dL, fc: FibreStepConstants, old: bool):
    """(A, p0, rhs, cM, cD) of the step equation (see FibreStepConstants)."""
    cM = fn * fc.cMd + fc.cM0
    cD = fn * fc.cDd + fc.cD0
    q0 = (L0 - fc.LR) - T * fc.inv_KSR
    A = dL * fc.KSR + T
    rhs = T * fc.inv_a2 + v * fc.rhs_v0 + dL * fc.rhs_dL + fn * fc.rhs_f1
    if old:
        A = A - v * fc.A_v0
        p0 = v * fc.p0_v0 + q0
        rhs = rhs + f * fc.rhs_f0
        if q0 > 0.0:
            start_damping = ((z * fc.c_mid + abs(z) * fc.c_half)
                             * (f * fc.beta_drive_old + fc.beta0_old) * (z * z) + fc.KPR) * q0
        else:  # no damping where the polar region is not longer than R
            start_damping = q0 * fc.KPR
    else:
        p0 = q0
        start_damping = q0 * fc.KPR
    rhs = rhs + fc.rhs_const - start_damping
    return A, p0, rhs, cM, cD


def _guess(z0: float, p0: float, rhs: float, cM: float, cD: float, fc: FibreStepConstants,
           k: StepConstants) -> float:
    """The frozen-factor guess of :func:`spindle.batch_step.frozen_guess` for one fibre."""
    abs_z0, z0_squared = abs(z0), z0 * z0
    if k.a_is_03:
        frozen = z0_squared * z0_squared * z0_squared * abs_z0
    else:
        frozen = abs_z0 ** (3.0 * fc.blend_exp)
    slope = (math.copysign(cD, rhs) + cM) * max(p0, 0.0) + frozen
    if not slope:
        return math.nan
    guess = math.cbrt(rhs / slope)
    blend = frozen * fc.blend_exp
    blend = blend / (slope + blend)
    return guess + (z0 - guess) * blend if z0 * guess > 0.0 else guess


def newton_float(z, p0, rhs, cM, cD, k, three_over_a, clip=False):
    """Newton on the step equation of :func:`spindle.batch_step.newton_loop` for one fibre;
    with ``clip`` the damping's polar-length factor q is clipped at 0 (where q <= 0,
    g = v - rhs)."""
    th_h = k.th_h
    th_h_10 = 10.0 * th_h
    a_is_03 = k.a_is_03
    power = three_over_a - 1.0
    dv_scale = three_over_a / 10.0
    dz = math.inf
    for _ in range(NEWTON_MAX_ITER):
        abs_z = abs(z)
        if a_is_03:
            sq = z * z
            t = sq * sq
            t = t * t * abs_z
        else:
            t = abs_z**power
        v = t * z
        damping = (cM * z + cD * abs_z) * z
        phi = damping * z
        q = v * th_h + p0
        if clip and q <= 0.0:
            g = v - rhs
            g_slope = 10.0 * t if a_is_03 else three_over_a * t
        else:
            g = phi * q + v - rhs
            g_slope = phi * th_h_10 + 10.0
            if not a_is_03:
                g_slope = g_slope * dv_scale
            g_slope = g_slope * t + damping * q * 3.0
        dz = g / max(g_slope, 1e-300)  # a NaN slope stays NaN (max keeps its first argument)
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


def afferents_one(T: list[float], L: float, c: FibreColumns) -> tuple[float, float]:
    """Ia and II (pps) of one spindle from its three fibre tensions, on floats (the
    arithmetic of :func:`spindle.core.afferents_from_tension`)."""
    (g0, n0), (g1, n1), (g2, n2) = c.primary_lin
    (a1, b1, c1), (a2, b2, c2) = c.secondary_lin
    x = max(T[0] * g0 - n0, 0.0)
    y = max(T[1] * g1 - n1, 0.0) + max(T[2] * g2 - n2, 0.0)
    ia = max(x, y) + min(x, y) * c.S
    ii = max(T[1] * a1 + L * b1 + c1, 0.0) + max(T[2] * a2 + L * b2 + c2, 0.0)
    return ia, ii
