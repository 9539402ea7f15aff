"""The implicit spindle step for many spindles at once: numpy, in place, in cached blocks.

This is the fast implementation of the step that :func:`spindle.core.plain_advance` writes
plainly; :func:`spindle.core.advance` uses it beyond :data:`spindle.float_step.SMALL_N` spindles
(it pays from there on: see :func:`spindle.core.advance`). Both solve the same equation to
the same tolerance and agree to rounding (~1e-13 pps).

- The step runs in blocks of CHUNK_SPINDLES spindles whose working arrays stay in cache, in
  place in buffers that each state keeps (its ``_workspace``, created on first use) and
  reuses from step to step. Each block iterates Newton until its own fibres have converged
  and hands the last few slow ones to a tail that finishes them together.
- The starting guess solves the step equation with |v|/|z|^3 frozen and blends it toward the
  previous z by the first-order correction for that freeze (:func:`frozen_guess`), which
  leaves most fibres two or three Newton iterations from convergence. Once a state has taken
  three steps of one size, the guess extrapolates its last three z instead (see
  :class:`Workspace`): as close, and some 20 passes over each block cheaper.
"""

from __future__ import annotations

import numpy as np

from spindle.fibre_constants import (
    MAX_DRIVE_POWER,
    NEWTON_FULL_ITER,
    NEWTON_MAX_DZ,
    NEWTON_MAX_ITER,
    NEWTON_TOL_Z,
    SpindleStepConstants,
    StepConstants,
    check_finite,
)

CHUNK_SPINDLES = 6144
"""Spindles per block of the vectorised step: every working array of a block stays in the
core's cache (the step makes ~150 passes over them), and each block leaves the Newton loop
as soon as all of its own fibres have converged."""

ROW_BY_ROW_SPINDLES = 6144
"""From this block width on, the start-of-step terms go fibre row by fibre row. Narrower
blocks do better with all rows at once (per step, one process: 1160 vs 1279 us at n = 1024,
1725 vs 1872 at 2048, 2028 vs 2069 at 4096; even at 6144 and 8192; shared 2-core machine,
2026-12-01)."""

TAIL_FRACTION = 8
"""A block hands its still-unconverged fibres to a common tail once at most 1/TAIL_FRACTION
of them remain (a few sign changes of v need more iterations than the rest)."""

TAIL_MIN_SPINDLES = 1024
"""From this many spindles on, blocks hand their slow fibres to the common tail; below,
a block iterates on (see :meth:`Workspace.advance`)."""

EXTRAPOLATE_SPINDLES = 8192
"""From this many spindles on, the guess extrapolates the last steps' z (see
:class:`Workspace`). The few fibres it leaves far off (mostly where v is about to cross 0)
go to the common tail, whose per-call cost outweighs the saving below this size."""

EXTRAPOLATE_MAX_ITER = 3.5
"""Mean Newton iterations per block above which a step's extrapolated guess counts as worse
than the frozen-factor one (which needs about 3): inputs noisy from sample to sample (length
noise of ~1e-4 L0 at 1 ms) make the extrapolation ring."""

EXTRAPOLATE_COOLDOWN = 64
"""Steps on the frozen-factor guess after such a step, before extrapolating again."""

HISTORY_PROBE = 61
"""Every this many spindles, the state's z is compared with the last step's output before
that step's history steers the next guess (see :class:`Workspace`)."""

_ALL = slice(None)
_MAX = np.maximum.reduce
_MIN = np.minimum.reduce
_ALL_TRUE = np.logical_and.reduce


def _spindle_vector(x, n: int) -> np.ndarray:
    """``x`` (a scalar or (n,)) as an (n,) array; an (n,) float array as it is."""
    if type(x) is np.ndarray and x.shape == (n,):
        return x
    return np.broadcast_to(x, (n,))


BUFFERS = (
    # start of the step (setup)
    "target",      # activation target a1 of the new drive
    "q0",          # polar length minus R at the start
    "z_squared",   # z0^2
    "frozen",      # the frozen factor |z0|^(3/a - 3) of the guess
    "slope",       # the frozen-factor equation's slope in z^3
    "blend",       # how far the guess moves back toward z0
    # the step equation (see newton_loop)
    "cM", "cD",    # damping coefficient cM + cD*sgn(z) of the new step
    "A",           # T1 = A - theta*h*KSR*v1
    "p0",          # new polar length minus R at v1 = 0
    "rhs",
    "p0_x3",       # 3*p0
    # Newton
    "z",           # the unknown
    "abs_z",       # |z|
    "v",           # v(z) = sgn(z)|z|^(3/a)
    "v_slope",     # |z|^(3/a - 1), then v'(z)
    "damping",     # the damping coefficient times z^2 (at the start: (KPR + D0)*q0)
    "g_slope",     # g'(z)
    "newton_step",  # g(z), then g/g'
    "tmp",         # one product term
)
"""The scratch arrays of a block, by role."""


class Block:
    """Scratch arrays for a block of ``w`` spindles: flat (3*w,) buffers and (3, w) views."""

    def __init__(self, w: int):
        self.w = w
        self.flat = {name: np.empty(3 * w) for name in BUFFERS}
        self.rows = {name: a.reshape(3, w) for name, a in self.flat.items()}
        self.dL = np.empty(w)
        self.moving = np.empty(3 * w, dtype=bool)
        self.same_sign = self.moving.reshape(3, w)
        self.drive_power = np.empty((3, w))
        self.drive_power_old = np.empty((3, w))
        self.k: StepConstants | None = None

    def prepare(self, k: StepConstants) -> None:
        """Expand the step's per-fibre constants that the Newton loop uses to (3*w,)."""
        if self.k is not k:
            w = self.w
            if k.per_spindle:  # a block's share of SpindleStepConstants: rows of (w,)
                def flat(name):
                    return np.broadcast_to(getattr(k.fibre_columns, name), (3, w)).reshape(-1)
            else:
                def flat(name):
                    return np.repeat([getattr(x, name) for x in k.fibre], w)
            self.th_h_KSR = flat("th_h_KSR")
            self.blend_exp = flat("blend_exp")
            e = flat("three_over_a")
            if k.per_spindle or not k.a_is_03:
                # the Newton slope's coefficient of v, (3 + 3/a)*theta*h
                self.flat["v_coef"] = (3.0 + e) * k.th_h
            if not k.a_is_03:
                # per-fibre exponents, expanded like the data (rows of w)
                self.flat["power"] = e - 1.0
                self.flat["three_over_a"] = e
            self.k = k


def workspace(state, k: StepConstants) -> Workspace:
    """The reusable buffers of ``state`` (kept on the state object, not a module global)."""
    ws = state.__dict__.get("_workspace")
    if ws is None or ws.n != state.n:
        ws = state.__dict__["_workspace"] = Workspace(state.n)
    ws.prepare(k)
    return ws


def advance_batched(state, L1, gd1, gs1, k: StepConstants):
    """:func:`spindle.core.advance` (implicit) for any number of spindles; returns the
    workspace's (T1, v1, z1, f1) buffers, valid until the next step of ``state``."""
    # a fibre at rest with its polar region no longer than R has no frozen-factor slope: its
    # guess divides by 0 and is then replaced (bound_guess); non-finite results are caught
    # by the finite check at the end of the step; g^p of a huge drive overflows to inf and
    # is capped (drive_powers). One errstate per step: each costs a few us.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return workspace(state, k).advance(state, L1, gd1, gs1)


class Workspace:
    """Reused buffers of the vectorised implicit step of one state (n spindles).

    :meth:`advance` returns the output arrays ``T1, v1, z1, f1`` themselves; they hold the
    result until the next ``advance`` of the same state.

    The z outputs rotate through four buffers, so the two before the latest stay available:
    once three steps of the same size have run (and n >= EXTRAPOLATE_SPINDLES), the Newton
    guess is the quadratic extrapolation 3*(z0 - z_-1) + z_-2 of the state's z and those two:
    3 passes over the block instead of the ~20 of :func:`frozen_guess`, and about as close
    (median error a few 1e-6 in z on smooth motion), except for a few percent of fibres whose
    v is about to cross 0, which end in the tail and start there again from the frozen-factor
    guess. The history only steers the guess: if the state was changed in between (a reset, a
    failed step, a step that was not committed), Newton still converges to the same
    tolerance, from farther away. A sample of the state's z is checked against the latest
    output (every HISTORY_PROBE-th spindle), so a state reset or edited between steps falls
    back to the frozen-factor guess instead of a far-off one, and a step whose blocks needed
    more than EXTRAPOLATE_MAX_ITER Newton iterations on average (inputs noisy from sample to
    sample) returns to it for EXTRAPOLATE_COOLDOWN steps.
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
        self.blocks = {m: Block(m)}
        if n % m:
            self.blocks[n % m] = Block(n % m)
        self.k: StepConstants | None = None

    def prepare(self, k: StepConstants | SpindleStepConstants) -> None:
        if k is not self.k or k.per_spindle:
            self.history = 0  # an extrapolation over a different step size is no guess
        self.k = k
        if not k.per_spindle:  # (else each block its share, see advance)
            for b in self.blocks.values():
                b.prepare(k)

    def advance(self, state, L1, gd1, gs1):
        k, n = self.k, self.n
        start = _StepStart.of(state, k)
        L1, gd1, gs1 = (_spindle_vector(x, n) for x in (L1, gd1, gs1))
        # An unchanged drive (the common case) has an unchanged activation target.
        same_drive = (k.theta < 1.0 and bool(_ALL_TRUE(np.equal(start.gd, gd1)))
                      and bool(_ALL_TRUE(np.equal(start.gs, gs1))))
        prior = self._extrapolation_history(start.z)
        tail = []
        iterations = 0
        # Below TAIL_MIN_SPINDLES a block's slow fibres iterate on in the block: the tail's
        # gathering costs more than the extra iterations there (per step, 1 ms, smooth
        # inputs, one process: 395 vs 317 us at n = 128, 640 vs 653 at 512, 749 vs 771 at
        # 1024, 1180 vs 1301 at 2048; shared 2-core machine, 2026-12-01). (Nor does a step
        # size per spindle use the tail, whose solver takes one.)
        hand_on = n >= TAIL_MIN_SPINDLES and not k.per_spindle
        for j0 in range(0, n, CHUNK_SPINDLES):
            cols = slice(j0, min(n, j0 + CHUNK_SPINDLES))
            b = self.blocks[cols.stop - j0]
            kb = k
            if k.per_spindle:
                kb = k.block(cols)
                b.prepare(kb)
            self._setup(b, cols, start, L1[cols], gd1[cols], gs1[cols], same_drive, kb,
                        guess=prior is None)
            if prior is not None:
                _extrapolate(start.z[:, cols], prior[0][:, cols], prior[1][:, cols], b.rows)
            clip = needs_clip(b.flat, kb)
            if clip:
                bound_guess(b.flat, kb)
            left, block_iterations = newton_block(b, kb, clip, hand_on)
            iterations += block_iterations
            if left is not None:
                tail.append(self._handed_on(b, left, j0, start.z))
            self._finish(b, cols)
        if tail:
            self._finish_tail(tail, restart=prior is not None)
        check_finite(self.T1, self.v1, k.h)
        ring = self.z_ring
        self.z_ring = [ring[3], ring[0], ring[1], ring[2]]
        self.history += 1
        n_blocks = len(range(0, n, CHUNK_SPINDLES))
        if prior is not None and iterations > EXTRAPOLATE_MAX_ITER * n_blocks:
            self.cooldown = EXTRAPOLATE_COOLDOWN  # rough inputs: the frozen guess does better
        return self.T1, self.v1, self.z1, self.f1

    def _extrapolation_history(self, z0):
        """(z_-1, z_-2) when this step may extrapolate its guess from them, else None; makes
        the oldest ring buffer this step's z output."""
        ring = self.z_ring
        self.z1 = ring[3]  # the oldest: no longer part of the history
        if self.n < EXTRAPOLATE_SPINDLES:
            return None
        if self.history and not np.array_equal(z0[:, ::HISTORY_PROBE],
                                               ring[0][:, ::HISTORY_PROBE]):
            self.history = 0  # the state is not the one the last step left
        self.cooldown = max(0, self.cooldown - 1)
        if self.history >= 3 and self.n >= EXTRAPOLATE_SPINDLES and not self.cooldown:
            return ring[1], ring[2]
        return None

    def _handed_on(self, b, left, j0, z0):
        """What the tail needs of the fibres (flat indices ``left``) a block handed on."""
        rows, idx = np.divmod(left, b.w)
        f = b.flat
        exponents = (f["power"], f["three_over_a"], f["v_coef"]) if not self.k.a_is_03 else ()
        return (rows * self.n + (idx + j0), z0[rows, idx + j0], b.blend_exp[left],
                *(x[left] for x in (f["z"], f["p0"], f["rhs"], f["cM"], f["cD"], f["A"],
                                    b.th_h_KSR, *exponents)))

    def _setup(self, b, cols, start, L1, gd1, gs1, same_drive, k, guess=True):
        """Everything known at the start of the step, and (with ``guess``) the frozen-factor
        guess. Wide blocks go fibre row by fibre row (the constants are then Python floats,
        cheaper to apply than broadcast columns); narrow ones all rows at once with (3, 1)
        columns (fewer calls). ``k``: the block's step constants."""
        old = k.theta < 1.0
        L0 = start.L[cols]
        dL = np.subtract(L1, L0, out=b.dL)
        by_row = b.w >= ROW_BY_ROW_SPINDLES
        power = drive_powers(gd1, gs1, k, b.drive_power, all_rows=not by_row)
        power_old = (None if same_drive or not old else
                     drive_powers(start.gd[cols], start.gs[cols], k, b.drive_power_old,
                                  all_rows=not by_row))
        if by_row:
            groups = [(i, k.fibre[i], k.lagged[i], power[k.drive_row[i]],
                       None if power_old is None else power_old[k.drive_row[i]])
                      for i in range(3)]
        else:
            # instantaneous fibres: keep = from_a0 = 0, from_a1 = 1 give f1 = a1 exactly
            groups = [(_ALL, k.fibre_columns, True, power, power_old)]
        for i, fc, lagged, g, g_old in groups:
            r = b.rows if i is _ALL else {name: b.rows[name][i] for name in _SETUP_BUFFERS}
            T, v, z0, f0 = (x[i, cols] for x in (start.T, start.v, start.z, start.f))
            f1 = self.f1[i, cols]
            _new_activation(f0, g, g_old, fc, lagged, old and same_drive, f1, r)
            _known_terms(T, v, z0, f0, f1, L0, dL, fc, old, r)
            if guess:
                frozen_guess(z0, r["abs_z"], r["z_squared"], r["rhs"], r["cM"], r["cD"],
                             r["p0"], fc.blend_exp, k.a_is_03, r, b.same_sign[i])

    def _finish(self, b, cols):
        """v1, T1 and z1 of a block from its last Newton iteration. That iteration moved z by
        dz (|dz| <= NEWTON_TOL_Z wherever the block converged; the tail rewrites the rest), so
        v(z) = v(z_prev) - v'(z_prev)*dz is exact to O(dz^2): below 1e-16 L0/s, v's rounding."""
        r = b.rows
        v1 = self.v1[:, cols]
        np.multiply(r["v_slope"], r["newton_step"], out=r["tmp"])
        np.subtract(r["v"], r["tmp"], out=v1)
        T1 = self.T1[:, cols]
        np.multiply(v1, b.th_h_KSR.reshape(3, -1), out=T1)
        np.subtract(r["A"], T1, out=T1)
        self.z1[:, cols] = r["z"]

    def _finish_tail(self, tail, restart):
        """Newton to convergence on the fibres the blocks handed over. With ``restart`` (their
        guess was extrapolated) they start again from the frozen-factor guess: an
        extrapolation that overshoots toward or across v = 0 leaves Newton far above a small
        root, where it creeps (each step removes only ~1/10 of the excess of z^10)."""
        idx, z0, blend_exp, z, p0, rhs, cM, cD, A, th_h_KSR, *exponents = (
            np.concatenate(x) for x in zip(*tail, strict=True))
        s = {name: np.empty(z.size) for name in BUFFERS}
        k = self.k
        if restart:
            s["z"] = z
            frozen_guess(z0, np.abs(z0), z0 * z0, rhs, cM, cD, p0, blend_exp, k.a_is_03, s,
                         np.empty(z.size, dtype=bool))
        s["z"] = z
        if exponents:
            s["power"], s["three_over_a"], s["v_coef"] = exponents
        s["p0"], s["rhs"] = p0, rhs
        clip = needs_clip(s, k)
        if clip:
            bound_guess(s, k)
        newton_loop(z, p0, rhs, cM, cD, k, s, first=0, clip=clip)
        v = velocity_into(z, s["abs_z"], s["v_slope"], s["v"], k, s.get("power"))
        self.z1.reshape(-1)[idx] = z
        self.v1.reshape(-1)[idx] = v
        self.T1.reshape(-1)[idx] = A - th_h_KSR * v


_SETUP_BUFFERS = ("target", "q0", "z_squared", "frozen", "slope", "blend", "cM", "cD", "A",
                  "p0", "rhs", "z", "abs_z", "damping", "tmp")


class _StepStart:
    """The state at the start of the step, fibre-major: T, v, z, f (3, n), L, gd, gs (n,)."""

    __slots__ = ("L", "T", "f", "gd", "gs", "v", "z")

    @classmethod
    def of(cls, state, k) -> _StepStart:
        start = cls()
        start.T, start.v, start.z, start.f = (a.T for a in (
            state.tension_FU, state.polar_velocity_L0_s, state.velocity_root, state.activation))
        start.L, start.gd, start.gs = state.length_L0, state.gamma_dyn_pps, state.gamma_stat_pps
        return start


def _extrapolate(z0, z_1, z_2, r) -> None:
    """The guess 3*(z0 - z_-1) + z_-2 into ``r["z"]``."""
    np.subtract(z0, z_1, out=r["tmp"])
    np.multiply(r["tmp"], 3.0, out=r["tmp"])
    np.add(r["tmp"], z_2, out=r["z"])


def _new_activation(f0, g, g_old, fc, lagged, same_target, f1, r) -> None:
    """f1 into ``f1`` from the drive powers g (new) and g_old (old, None when unchanged or
    theta = 1), and the new step's damping coefficients cM, cD into ``r``."""
    mul, add = np.multiply, np.add
    tmp, target = r["tmp"], r["target"]
    if lagged:
        add(g, fc.freq_p, out=target)
        np.divide(g, target, out=target)
        mul(f0, fc.keep, out=f1)
        if same_target:
            mul(target, fc.from_a0 + fc.from_a1, out=tmp)
            add(f1, tmp, out=f1)
        else:
            if g_old is not None:
                add(g_old, fc.freq_p, out=tmp)
                np.divide(g_old, tmp, out=tmp)
                mul(tmp, fc.from_a0, out=tmp)
                add(f1, tmp, out=f1)
            mul(target, fc.from_a1, out=tmp)
            add(f1, tmp, out=f1)
    else:
        add(g, fc.freq_p, out=tmp)
        np.divide(g, tmp, out=f1)
    cM, cD = r["cM"], r["cD"]
    mul(f1, fc.cMd, out=cM)
    add(cM, fc.cM0, out=cM)
    mul(f1, fc.cDd, out=cD)
    add(cD, fc.cD0, out=cD)


def _known_terms(T, v, z0, f0, f1, L0, dL, fc, old, r) -> None:
    """q0, A, p0, rhs of the step equation (see FibreStepConstants) into ``r``, with |z0|
    and z0^2 into ``r["abs_z"]``, ``r["z_squared"]``."""
    mul, add, sub = np.multiply, np.add, np.subtract
    tmp = r["tmp"]
    q0, A, p0, rhs = r["q0"], r["A"], r["p0"], r["rhs"]
    sub(L0, fc.LR, out=q0)
    mul(T, fc.inv_KSR, out=tmp)
    sub(q0, tmp, out=q0)
    mul(dL, fc.KSR, out=A)
    add(A, T, out=A)
    mul(T, fc.inv_a2, out=rhs)
    mul(v, fc.rhs_v0, out=tmp)
    add(rhs, tmp, out=rhs)
    mul(dL, fc.rhs_dL, out=tmp)
    add(rhs, tmp, out=rhs)
    mul(f1, fc.rhs_f1, out=tmp)
    add(rhs, tmp, out=rhs)
    abs_z, z_squared, start_damping = r["abs_z"], r["z_squared"], r["damping"]
    np.abs(z0, out=abs_z)
    mul(z0, z0, out=z_squared)
    if old:
        mul(v, fc.A_v0, out=tmp)
        sub(A, tmp, out=A)
        mul(v, fc.p0_v0, out=p0)
        add(p0, q0, out=p0)
        mul(f0, fc.rhs_f0, out=tmp)
        add(rhs, tmp, out=rhs)
        # (KPR + D0)*q0, D0 the damping factor of the force at the start
        mul(z0, fc.c_mid, out=start_damping)
        mul(abs_z, fc.c_half, out=tmp)
        add(start_damping, tmp, out=start_damping)
        mul(f0, fc.beta_drive_old, out=tmp)
        add(tmp, fc.beta0_old, out=tmp)
        mul(start_damping, tmp, out=start_damping)
        mul(start_damping, z_squared, out=start_damping)
        add(start_damping, fc.KPR, out=start_damping)
        mul(start_damping, q0, out=start_damping)
        if q0.min() <= 0.0:  # no damping where the polar region is not longer than R
            np.copyto(start_damping, q0 * fc.KPR, where=q0 <= 0.0)
    else:
        p0[...] = q0
        mul(q0, fc.KPR, out=start_damping)
    add(rhs, fc.rhs_const, out=rhs)
    sub(rhs, start_damping, out=rhs)


def frozen_guess(z0, abs_z0, z0_squared, rhs, cM, cD, p0, blend_exp, a_is_03, s, same_sign):
    """The Newton guess from the start of the step, into ``s["z"]``; ``s`` holds the scratch
    arrays "frozen", "slope", "blend", "tmp" shaped like z0, ``same_sign`` a bool array of
    that shape.

    g with |v|/|z^3| frozen at its previous value |z0|^7 (a = 0.3) is linear in z^3; its root
    already has the right sign and, near v = 0 and in holds where the trapezoidal rule rings,
    the right size, which the previous z has not.
    """
    mul, add = np.multiply, np.add
    frozen, slope, blend, z, tmp = s["frozen"], s["slope"], s["blend"], s["z"], s["tmp"]
    if a_is_03:
        mul(z0_squared, z0_squared, out=frozen)
        mul(frozen, z0_squared, out=frozen)
        mul(frozen, abs_z0, out=frozen)
    else:
        np.power(abs_z0, blend_exp * 3.0, out=frozen)
    np.copysign(cD, rhs, out=slope)
    add(slope, cM, out=slope)
    np.maximum(p0, 0.0, out=blend)
    mul(slope, blend, out=slope)
    add(slope, frozen, out=slope)
    np.divide(rhs, slope, out=z)
    np.cbrt(z, out=z)
    # The frozen factor's error: log z_guess - log z ~ e*s*(log z - log z0), e the exponent
    # of |z| in it (7/3 for a = 0.3) and s the share of the |v| term in the slope; solving
    # that to first order blends the guess toward z0 by e*s/(1 + e*s). Only where z0 and the
    # guess share a sign (v does not reverse).
    mul(frozen, blend_exp, out=blend)
    add(slope, blend, out=tmp)
    np.divide(blend, tmp, out=blend)
    mul(z0, z, out=tmp)
    np.greater(tmp, 0.0, out=same_sign)
    mul(blend, same_sign, out=blend)
    np.subtract(z0, z, out=tmp)
    mul(tmp, blend, out=tmp)
    add(z, tmp, out=z)
    return z


def drive_powers(gd, gs, k, out, all_rows=False):
    """g^p of each fibre's drive into the rows of ``out`` that ``k.drive_row`` names (into
    every row with ``all_rows``); capped at MAX_DRIVE_POWER (the caller ignores the
    overflow: :func:`advance_batched`)."""
    for row, (g, p) in enumerate(zip((gd, gs, gs), k.p, strict=True)):
        if row in k.drive_row:
            if p == 2.0:
                np.multiply(g, g, out=out[row])
            else:
                np.power(g, p, out=out[row])
            np.minimum(out[row], MAX_DRIVE_POWER, out=out[row])
        elif all_rows:
            out[row] = out[k.drive_row[row]]
    return out


def velocity_into(z, abs_z, v_slope, v, k, power=None):
    """v = sgn(z)|z|^(3/a) into ``v``, with |z| in ``abs_z`` and |z|^(3/a - 1) in
    ``v_slope`` (``power`` holds 3/a - 1 unless a = 0.3, where it is z^8*|z|: no fractional
    power)."""
    np.abs(z, out=abs_z)
    if k.a_is_03:
        np.multiply(z, z, out=v_slope)
        np.multiply(v_slope, v_slope, out=v_slope)
        np.multiply(v_slope, v_slope, out=v_slope)
        np.multiply(v_slope, abs_z, out=v_slope)
    else:
        np.power(abs_z, power, out=v_slope)
    np.multiply(v_slope, z, out=v)
    return v


def needs_clip(s, k) -> bool:
    """Whether the new polar region of any fibre in ``s`` (flat arrays "p0", "rhs") may end
    no longer than R, where the damping's clip at 0 enters the step equation. At the root
    |v| <= |rhs| (the damping term has the sign of v), so q = p0 + theta*h*v >= 0 wherever
    p0 > theta*h*|rhs|: everywhere but near the short end of the length range (three
    reductions per block)."""
    # (the ufuncs' reduce directly: the ndarray methods add a Python layer per call)
    return bool(_MIN(s["p0"]) <= k.th_h_max * _MAX(np.abs(s["rhs"], out=s["tmp"])))


def bound_guess(s, k) -> None:
    """Replace guesses beyond the root's bound |z| <= |rhs|^(a/3) (and NaN ones: with v = 0
    and p0 <= 0 the frozen-factor guess has no slope) by the bound, in ``s["z"]``."""
    z, rhs = s["z"], s["rhs"]
    exponent = 0.1 if k.a_is_03 else 1.0 / s["three_over_a"]
    bound = np.abs(rhs) ** exponent
    far = ~(np.abs(z) <= bound)
    z[far] = np.copysign(bound, rhs)[far]


def newton_block(b, k, clip=False, hand_on=True):
    """Newton on one block; returns (the flat indices handed to the tail or None, the number
    of iterations). Without ``hand_on`` the block iterates until all its fibres converged."""
    f = b.flat
    return newton_loop(f["z"], f["p0"], f["rhs"], f["cM"], f["cD"], k, f,
                       first=NEWTON_FULL_ITER - 1, moving=b.moving if hand_on else None,
                       clip=clip)


def newton_loop(z, p0, rhs, cM, cD, k, s, first, moving=None, clip=False):
    """Newton's method on the step equation for z, in place, until every |dz| <= 1e-9.

    The unknown is z = sgn(v)|v|^(a/3): the damping sgn(v)|v|^a is z^3 and v = sgn(z)|z|^(3/a)
    (z^10 for a = 0.3), both polynomials, so no iteration evaluates a fractional power. With
    v = v1 and T1 = A - theta*h*KSR*v (A holds everything known, see
    :class:`spindle.fibre_constants.FibreStepConstants`), the step equation
    M*(v1 - v0)/h = (1 - theta)*F0 + theta*F1 divided by a2 reads

        g(z) = v + Cb(z)*z^3*(p0 + theta*h*v) - rhs = 0

    with Cb = theta*C*beta1/a2 = cM + cD*sgn(z) (C = CL for z > 0, CS else) and p0 the new
    polar length minus R at v = 0. g rises monotonically (convex for z > 0, concave below)
    wherever the polar region is longer than R, so Newton converges after at most one
    overshoot; steps are capped at NEWTON_MAX_DZ, which also covers g' = 0 at z = 0.

    With ``clip`` the damping's factor q (the new polar length minus R) is clipped at 0, the
    model's rule (see :mod:`spindle.core`): where q <= 0, g = v - rhs. g then rises
    monotonically everywhere; without ``clip`` the caller has made sure q > 0 at the root
    (:func:`needs_clip`), where both equations agree.

    ``s`` holds scratch arrays shaped like z (see :data:`BUFFERS`). From iteration ``first``
    on, if at most 1/TAIL_FRACTION of the fibres still move (|dz| > tolerance), their flat
    indices are returned and the caller finishes them together with other blocks' (a few
    fibres whose v reverses need more iterations than the rest); else None once all have
    converged. The second value returned is the number of iterations.
    """
    # g' = v'(z)*(1 + theta*h*phi) + 3*damping*q with phi = damping*z and
    # v' = (3/a)|z|^(3/a - 1), so phi*v' = (3/a)*damping*v and
    # g' = v' + damping*(3*p0 + (3 + 3/a)*theta*h*v); 3*p0 is fixed.
    np.multiply(p0, 3.0, out=s["p0_x3"])
    for iteration in range(NEWTON_MAX_ITER):
        largest = _newton_iteration(z, p0, rhs, cM, cD, k, s, clip)
        if largest <= NEWTON_TOL_Z:
            return None, iteration + 1
        if moving is not None and iteration >= first:
            # g_slope holds |dz| (see _newton_iteration)
            np.greater(s["g_slope"], NEWTON_TOL_Z, out=moving)
            left = np.flatnonzero(moving)
            if left.size <= moving.size // TAIL_FRACTION:
                # none left: the only fibres not converged are NaN, which the finite check
                # after the step reports
                return (left if left.size else None), iteration + 1
    raise FloatingPointError(
        f"implicit spindle step did not converge in {NEWTON_MAX_ITER} iterations "
        f"(last change in z {largest:.3g}); state left unchanged"
    )


def _newton_iteration(z, p0, rhs, cM, cD, k, s, clip):
    """One Newton step on g(z) (see :func:`newton_loop`), in place in ``z``; returns the
    largest and smallest step taken (before the cap)."""
    mul, add = np.multiply, np.add
    # 12 arrays in all, so that a block's stay in the core's cache
    v_slope, v, abs_z, damping, step, g_slope, p0_x3 = (s[name] for name in (
        "v_slope", "v", "abs_z", "damping", "newton_step", "g_slope", "p0_x3"))
    velocity_into(z, abs_z, v_slope, v, k, None if k.a_is_03 else s["power"])
    # damping = Cb*z^2 with Cb = theta*C*beta1 (C = CL for z > 0, CS else)
    mul(cM, z, out=damping)
    mul(cD, abs_z, out=g_slope)
    add(damping, g_slope, out=damping)
    mul(damping, z, out=damping)
    # g = v + damping*z*q - rhs with q = p0 + theta*h*v, into step
    mul(v, k.th_h, out=step)
    add(step, p0, out=step)
    if clip:
        undamped = step <= 0.0
        np.maximum(step, 0.0, out=step)
    mul(step, damping, out=step)
    mul(step, z, out=step)
    add(step, v, out=step)
    np.subtract(step, rhs, out=step)
    mul(v_slope, 10.0 if k.a_is_03 else s["three_over_a"], out=v_slope)  # now v'(z)
    mul(v, 13.0 * k.th_h if k.a_is_03 and not k.per_spindle else s["v_coef"], out=g_slope)
    add(g_slope, p0_x3, out=g_slope)
    mul(g_slope, damping, out=g_slope)
    add(g_slope, v_slope, out=g_slope)
    if clip:
        np.copyto(g_slope, v_slope, where=undamped)
    np.maximum(g_slope, 1e-300, out=g_slope)
    np.divide(step, g_slope, out=step)  # now dz
    # the largest |dz| (NaN if any is): one reduction, not a max and a min
    largest = _MAX(np.abs(step, out=g_slope))
    if largest > NEWTON_MAX_DZ:
        np.clip(step, -NEWTON_MAX_DZ, NEWTON_MAX_DZ, out=step)
    np.subtract(z, step, out=z)
    return largest
