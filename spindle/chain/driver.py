"""The spindles of every muscle of every env, advanced together: one batched spindle state.

A bank holds ``n_rows`` rows (envs) of ``n_muscles`` spindles each, one
:class:`spindle.core.SpindleState` of ``n_rows * n_muscles`` spindles (row-major: env i,
muscle j is spindle ``i * n_muscles + j``). Each env step feeds it *knots*: the normalised
lengths and velocities at equally spaced times across the step, the last at its end (the
state after every physics step, or points of a Hermite curve when those are unknown). Per
knot interval, the spindles take equal sub-steps of at most ``step_s`` (1 ms for the
trapezoidal method) along the Hermite curve through the knots and their velocities
(:func:`spindle.substeps.substep_lengths`), with the fusimotor drive of the knot that ends the
interval (as the prosthesis chain does per sample).

Handling rules (counted per spindle in :attr:`SpindleDriver.counters`; never a NaN):

- ``length_clamped``: a knot's length outside the spindle's range
  (:data:`spindle.core.LENGTH_RANGE_L0`, 0.5-1.5 L0) is clamped to it (its velocity taken as
  0 there, so the curve stays on the bound);
- ``slew_limited``: a knot's length that moved faster than ``max_speed_L0_s`` since the
  previous one (default 8 L0/s, the chain's limit, below the spindle's 10 L0/s) is limited
  to that speed; knot velocities are clipped to it too;
- ``substeps_limited`` (one total per bank, from ``substep_lengths``): sub-step lengths of the
  curve held within the range and the speed limit;
- ``restarts``: a spindle step that fails (no convergence, a non-finite value) restarts every
  spindle of the bank at equilibrium at the knot's lengths (never seen; the rule keeps a
  training run alive).

Backends: ``"numpy"`` steps the bank's :class:`spindle.core.SpindleState` with
:func:`spindle.core.advance` (one call per sub-step for every spindle of every row); ``"c"``
keeps the spindles in one C array (:class:`spindle.native.spindle.CSpindleBatch`, one
``ps_spindle_batch_steps`` call for all the sub-steps of an env step, one
``ps_spindle_batch_step`` per sub-step when every knot's rates are recorded); ``"auto"``
is C when the library builds or loads here (:func:`spindle.chain.resolve_backend`). Both take
the same sub-step lengths and drives; their rates agree to ~1e-10 pps (the C step multiplies
by reciprocals where numpy divides). Only the trapezoidal family (theta > 0) runs in C.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from spindle import core
from spindle.backends import DEFAULT_BACKEND, implementation, resolve_backend
from spindle.chain.fusimotor import SEED_PAPER, Fusimotor, FusimotorParams
from spindle.methods import get_method
from spindle.number_rule import real_scalar
from spindle.params import HUMAN, SpindleParams
from spindle.renamed import renamed_attribute
from spindle.substeps import slew_limited, substep_lengths, substeps

COUNTERS = ("length_clamped", "slew_limited")
"""Per-spindle counters of :class:`SpindleDriver` (shape (n_rows, n_muscles))."""


@dataclass(frozen=True)
class ConstantFusimotor:
    """A constant fusimotor drive (the default).

    The defaults are the seed paper's fusimotor model at rest at the middle of a muscle's
    range: h(x) = 20 + 130 * 0.5 = 85 pps static, g(x) = 100 pps dynamic (a muscle that is
    not shortening). A constant drive makes the afferents a function of the muscle's motion
    alone, which is what a controller learning from them can rely on.

    Attributes:
        gamma_static_pps, gamma_dynamic_pps: scalars, or one value per muscle.
    """

    gamma_static_pps: float | tuple[float, ...] = 85.0
    gamma_dynamic_pps: float | tuple[float, ...] = 100.0

    def __post_init__(self) -> None:
        for name in ("gamma_static_pps", "gamma_dynamic_pps"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim > 1 or not np.all(np.isfinite(value)) or np.any(value < 0):
                raise ValueError(f"{name}={getattr(self, name)!r} must be finite and >= 0 "
                                 "(a scalar or one value per muscle)")


@dataclass(frozen=True)
class TemplateFusimotor:
    """The seed paper's fusimotor model per muscle: the PI template of each muscle's length,
    gamma_s = h(x) and gamma_d = g(x) (:class:`spindle.chain.fusimotor.Fusimotor`).

    Attributes:
        params: the model's constants (default: the seed paper's).
        length_min_L0, length_max_L0: h(x)'s Lmin and Lmax per muscle; ``None``: the
            muscle's ``range`` (the normalised image of MuJoCo's ``lengthrange``, the length
            range over the model's range of motion when the compiler computed it).
    """

    params: FusimotorParams = SEED_PAPER
    length_min_L0: tuple[float, ...] | None = None
    length_max_L0: tuple[float, ...] | None = None


class SpindleDriver:
    """``n_rows`` x ``n_muscles`` spindles, reset and advanced row-wise in one batched state.

    Args:
        n_rows: envs.
        length_min_L0, length_max_L0: (n_muscles,) each muscle's length range (the template
            fusimotor's h(x) span).
        params: spindle constants (default :data:`spindle.HUMAN`).
        fusimotor: :class:`ConstantFusimotor` or :class:`TemplateFusimotor`.
        method: the spindle integrator (default trapezoidal).
        step_s: largest spindle sub-step (s); ``None``: the method's default (1 ms).
        max_speed_L0_s: the knots' slew limit (L0/s).
        backend: ``"numpy"``, ``"c"`` or ``"auto"`` (see the module docstring).
    """

    def __init__(self, n_rows: int, length_min_L0: np.ndarray, length_max_L0: np.ndarray,
                 params: SpindleParams = HUMAN,
                 fusimotor: ConstantFusimotor | TemplateFusimotor | None = None,
                 method: str = "trapezoidal", step_s: float | None = None,
                 max_speed_L0_s: float = core.SLEW_LIMIT_L0_S,
                 backend: str = DEFAULT_BACKEND) -> None:
        self.n_rows = int(n_rows)
        self.n_muscles = int(np.size(length_min_L0))
        if self.n_rows < 1 or self.n_muscles < 1:
            raise ValueError(f"a bank needs rows and muscles, got {n_rows} x {self.n_muscles}")
        self.params = params
        self.fusimotor = ConstantFusimotor() if fusimotor is None else fusimotor
        self._method = get_method(method)
        # spindle.number_rule: a Python float, never "0.001", True or a float32 kept as such
        self.step_s = core.check_step(self._method.default_step_s if step_s is None else step_s,
                                      self._method, "step_s")
        self.max_speed_L0_s = real_scalar("max_speed_L0_s", max_speed_L0_s, low=0.0,
                                          low_open=True, high=core.MAX_SPEED_L0_S)
        self._columns = core.columns(params)
        shape = (self.n_rows, self.n_muscles)
        if isinstance(self.fusimotor, TemplateFusimotor):
            f = self.fusimotor
            lo = np.broadcast_to(np.asarray(
                length_min_L0 if f.length_min_L0 is None else f.length_min_L0, float),
                (self.n_muscles,))
            hi = np.broadcast_to(np.asarray(
                length_max_L0 if f.length_max_L0 is None else f.length_max_L0, float),
                (self.n_muscles,))
            self._templates = Fusimotor(lo, hi, f.params, self.n_rows)
            self._gs = np.zeros(shape)
            self._gd = np.zeros(shape)
        elif isinstance(self.fusimotor, ConstantFusimotor):
            self._templates = None
            self._gs = np.broadcast_to(np.asarray(self.fusimotor.gamma_static_pps, float),
                                       shape).copy()
            self._gd = np.broadcast_to(np.asarray(self.fusimotor.gamma_dynamic_pps, float),
                                       shape).copy()
        else:
            raise ValueError(f"fusimotor={self.fusimotor!r} must be a ConstantFusimotor or a "
                             "TemplateFusimotor")
        n = self.n_rows * self.n_muscles
        self.backend = resolve_backend(backend)
        self._state = core.equilibrium_state(np.ones(n), self._gd.ravel(), self._gs.ravel(),
                                             params)
        self._batch = None
        if self.backend == "c":
            self._batch = implementation("spindle_batch", "c")[1](
                self._state, params, self.step_s, self._method.theta)
        self.length_L0 = np.ones(shape)      # the last knot as fed (clamped, slew-limited)
        self.velocity_L0_s = np.zeros(shape)
        self.t_s = np.zeros(self.n_rows)
        self.ia_pps, self.ii_pps = (a.reshape(shape) for a in core.afferents(self._state, params))
        self.counters = {name: np.zeros(shape, dtype=np.int64) for name in COUNTERS}
        self.restarts = 0
        self._all_rows = np.ones(self.n_rows, bool)
        self._all_rows.flags.writeable = False
        self._constant_drive: tuple[np.ndarray, np.ndarray] | None = None
        self.substeps_limited = 0

    # -- copies and pickling: the C array travels as a plain-array state ----------------
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        if self._batch is not None:  # ctypes objects with pointers cannot be pickled
            state["_state"], state["_batch"] = self._batch.state(), None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        if self.backend == "c":
            self._batch = implementation("spindle_batch", "c")[1](
                self._state, self.params, self.step_s, self._method.theta)

    @property
    def state(self) -> core.SpindleState:
        """The spindles' state (rows x muscles, row-major): numpy, the bank's own; C, a copy."""
        return self._state if self._batch is None else self._batch.state()

    @property
    def gamma_static_pps(self) -> np.ndarray:
        return self._gs.copy()

    @property
    def gamma_dynamic_pps(self) -> np.ndarray:
        return self._gd.copy()

    # -- reset ---------------------------------------------------------------------------
    def reset(self, rows: np.ndarray | None, t_s: np.ndarray, length_L0: np.ndarray,
              velocity_L0_s: np.ndarray | None = None) -> None:
        """Rows ``rows`` (None: all) at rest at ``length_L0`` (m, n_muscles) at ``t_s`` (m,):
        their spindles at equilibrium with the drive at that length; their counters to 0
        (then the clamp of the reset lengths counted). ``velocity_L0_s`` is kept as the
        curve's start velocity of the next step (default 0)."""
        rows = np.arange(self.n_rows) if rows is None else np.asarray(rows, dtype=int)
        if rows.size == 0:
            return
        raw = np.asarray(length_L0, dtype=float).reshape(rows.size, self.n_muscles)
        L, clamped = self._clamp(raw)
        V = (np.zeros_like(L) if velocity_L0_s is None
             else np.asarray(velocity_L0_s, float).reshape(L.shape))
        V = np.where(clamped, 0.0, np.clip(V, -self.max_speed_L0_s, self.max_speed_L0_s))
        t = np.broadcast_to(np.asarray(t_s, dtype=float), (rows.size,))
        if self._templates is not None:
            _, self._gs[rows], self._gd[rows] = self._templates.reset(t, L, rows)
        for name in COUNTERS:
            self.counters[name][rows] = 0
        self.counters["length_clamped"][rows] += clamped
        idx = (rows[:, None] * self.n_muscles + np.arange(self.n_muscles)).ravel()
        rest = core.equilibrium_state(L.ravel(), self._gd[rows].ravel(), self._gs[rows].ravel(),
                                      self.params)
        self._load(rest, idx)
        self.length_L0[rows], self.velocity_L0_s[rows], self.t_s[rows] = L, V, t
        ia, ii = core.afferents(rest, self.params)
        self.ia_pps[rows], self.ii_pps[rows] = (a.reshape(L.shape) for a in (ia, ii))

    # -- advance -------------------------------------------------------------------------
    def advance(self, t_s: np.ndarray, length_L0: np.ndarray, velocity_L0_s: np.ndarray,
                hold: np.ndarray | None = None, record: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
        """Advance every row through K knots; returns (Ia, II) in pps, (n_rows, n_muscles).

        Args:
            t_s: (K, n_rows) knot times, equally spaced by the same interval in every row,
                the first one interval after each row's last knot.
            length_L0, velocity_L0_s: (K, n_rows, n_muscles) normalised lengths and
                velocities at the knots, as measured (the rules above apply here).
            hold: (n_rows,) bool, rows that did not move this step (e.g. about to be reset):
                they are fed their last knot again and their counters are left alone.
            record: keep every knot's rates, fed lengths and drive in :attr:`knots`
                (a dict of (K, n_rows, n_muscles) arrays).
        """
        t = np.asarray(t_s, dtype=float)
        K = t.shape[0]
        shape = (K, self.n_rows, self.n_muscles)
        raw = np.asarray(length_L0, dtype=float).reshape(shape)
        V = np.asarray(velocity_L0_s, dtype=float).reshape(shape)
        if hold is not None and not np.any(hold):
            hold = None  # every row moves (the rules' short paths below)
        if hold is not None:
            raw = np.where(hold[None, :, None], self.length_L0[None], raw)
            V = np.where(hold[None, :, None], 0.0, V)
        first = t[0] - self.t_s
        moving = self._all_rows if hold is None else ~np.asarray(hold, bool)
        dt = self._interval(t, first, moving)
        L, clamped = self._clamp(raw)
        V = self._clip_velocity(V, clamped)
        L, slewed = self._slew(L, dt)
        for name, hit in (("length_clamped", clamped), ("slew_limited", slewed)):
            if np.count_nonzero(hit):  # (a third of .any()'s reduction: 2 us a legs step)
                self.counters[name] += (hit if hold is None
                                        else hit & moving[None, :, None]).sum(axis=0)
        gs, gd = self._drive(t, L, moving)  # (K, n_rows, n_muscles) each
        n = self.n_rows * self.n_muscles
        k = substeps(dt, self.step_s)
        if k == 1:
            # one sub-step per knot interval ends on the knot (substep_lengths' k = 1 case,
            # without the knots' concatenation and copy: 3 of the legs' ~30 us of rules)
            sub = L.reshape(K, n)
        else:
            knots = np.concatenate((self.length_L0.reshape(1, n), L.reshape(K, n)))
            slopes = [np.concatenate((self.velocity_L0_s.reshape(1, n), V.reshape(K, n)))]
            sub, changed = substep_lengths(knots, slopes, k, dt)
            self.substeps_limited += changed
        ia, ii = self._integrate(sub, gs.reshape(K, n), gd.reshape(K, n), k, dt / k, record)
        if record:
            rates = self._recorded
            self.knots = {"ia_pps": rates[0].reshape(shape), "ii_pps": rates[1].reshape(shape),
                          # copies: without a clamp or slew L and V are the caller's arrays
                          "length_L0": L.copy(), "velocity_L0_s": V.copy(),
                          "gamma_static_pps": gs,
                          "gamma_dynamic_pps": gd}
        self.length_L0[...], self.velocity_L0_s[...] = L[-1], V[-1]
        self.t_s = t[-1].copy() if hold is None else np.where(moving, t[-1], self.t_s)
        if self._templates is not None:  # a constant drive stays as it is
            self._gs[...], self._gd[...] = gs[-1], gd[-1]
        self.ia_pps, self.ii_pps = ia.reshape(self.n_rows, -1), ii.reshape(self.n_rows, -1)
        return self.ia_pps, self.ii_pps

    def _integrate(self, sub: np.ndarray, gs: np.ndarray, gd: np.ndarray, k: int, h: float,
                   record: bool = False):
        K = gs.shape[0]
        if record:
            self._recorded = (np.empty((K, sub.shape[1])), np.empty((K, sub.shape[1])))
        q = 0
        try:
            if self._batch is None:
                ia, ii = self._integrate_numpy(sub, gs, gd, k, h, record)
            else:
                ia, ii = self._integrate_c(sub, gs, gd, k, h, record)
        except FloatingPointError:
            self.restarts += 1
            rest = core.equilibrium_state(sub[-1], gd[-1], gs[-1], self.params)
            self._load(rest, None)
            ia, ii = core.afferents(rest, self.params)
            if record:
                q = self._recorded_upto
                self._recorded[0][q:], self._recorded[1][q:] = ia, ii
            return ia, ii
        return ia, ii

    def _integrate_numpy(self, sub, gs, gd, k, h, record):
        c, theta, state = self._columns, self._method.theta, self._state
        new = None
        self._recorded_upto = 0
        for j in range(sub.shape[0]):
            Ls, q = sub[j], j // k
            new = core.advance(state, Ls, gd[q], gs[q], h, theta, c)
            core.commit(state, new, Ls, gd[q], gs[q])
            if record and j % k == k - 1:
                self._recorded[0][q], self._recorded[1][q] = \
                    core.afferents_from_tension(new[0], Ls, c)
                self._recorded_upto = q + 1
        if record:
            return self._recorded[0][-1].copy(), self._recorded[1][-1].copy()
        # the rates only at the end: the observation needs no others
        return core.afferents_from_tension(new[0], sub[-1], c)

    def _integrate_c(self, sub, gs, gd, k, h, record):
        batch = self._batch
        batch.set_step(h)
        last = sub.shape[0] - 1
        self._recorded_upto = 0
        if not record:  # the rates only at the end: every sub-step in one C call
            gd_sub, gs_sub = ((np.repeat(x, k, axis=0) for x in (gd, gs)) if k > 1
                              else (gd, gs))
            ia, ii = batch.steps(sub, gd_sub, gs_sub)
            return ia.copy(), ii.copy()
        gs_rows = np.ascontiguousarray(gs)
        gd_rows = np.ascontiguousarray(gd)
        for j in range(sub.shape[0]):
            q = j // k
            rates = j == last or (record and j % k == k - 1)
            ia, ii = batch.step(sub[j], gd_rows[q], gs_rows[q], rates)
            if record and j % k == k - 1:
                self._recorded[0][q], self._recorded[1][q] = ia, ii
                self._recorded_upto = q + 1
        return ia.copy(), ii.copy()

    def _load(self, rest: core.SpindleState, idx: np.ndarray | None) -> None:
        """Spindles ``idx`` (None: all) to the state ``rest``."""
        if self._batch is not None:
            self._batch.load(rest, idx)
            return
        for name in core.STATE_FIELDS:
            target = getattr(self._state, name)
            if idx is None:
                target[...] = getattr(rest, name)
            else:
                target[idx] = getattr(rest, name)

    # -- rules ---------------------------------------------------------------------------
    def _interval(self, t: np.ndarray, first: np.ndarray, moving: np.ndarray) -> float:
        """The knot interval (s) of the moving rows (``first``: each row's first knot less its
        last one); ValueError unless it is finite, > 0 and the same in every moving row."""
        some = moving is self._all_rows or moving.any()
        dt = float(first[0] if moving is self._all_rows or not some else first[moving][0])
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"knot interval {dt!r} s must be finite and > 0")
        # (plus the resolution of the rows' clocks: an env's clock set far forward); one row
        # cannot differ from itself
        if self.n_rows > 1 and some and np.abs(first[moving] - dt).max() > \
                1e-9 * max(dt, 1.0) + 4 * np.spacing(np.abs(t[0][moving]).max()):
            raise ValueError(f"knot intervals differ between rows ({first[moving].tolist()} "
                             "s); every row must take knots at the same interval")
        return dt

    @staticmethod
    def _clamp(L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = core.LENGTH_RANGE_L0
        # a NaN length (a diverged simulation) is out of range too: it goes to the low end
        # (fmax takes lo over a NaN); out of range is where the length changed (a NaN is
        # unequal to all). Three ufuncs for np.clip, isnan, where and four comparisons: 7 of
        # 10 us on myo-sim's legs, where some muscle is always out of range
        out = np.minimum(np.fmax(L, lo), hi)
        return out, out != L

    def _clip_velocity(self, V: np.ndarray, clamped: np.ndarray) -> np.ndarray:
        """Knot velocities clipped to the slew limit, 0 where the length was clamped."""
        limit = self.max_speed_L0_s
        # np.clip's ufuncs without its Python wrapper (a NaN stays one, as with np.clip)
        return np.where(clamped, 0.0, np.minimum(np.maximum(V, -limit), limit))

    def _slew(self, L: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
        return slew_limited(L, self.length_L0, self.max_speed_L0_s * dt, axis=0)

    def _drive(self, t: np.ndarray, L: np.ndarray, moving: np.ndarray):
        """(gamma_s, gamma_d) at every knot (K, n_rows, n_muscles): the bank's constant drive,
        or every moving row's template (one :class:`~spindle.chain.fusimotor.Fusimotor` over
        the rows, as the chain's); a held row keeps its last drive."""
        K = t.shape[0]
        if self._templates is None:
            # a constant drive: the same (K, rows, muscles) arrays every step, made once
            # (read-only, contiguous, so the C step takes them without a copy: two
            # broadcasts and two copies were 12 of the legs' ~30 us of rules)
            if self._constant_drive is None or self._constant_drive[0].shape[0] != K:
                self._constant_drive = tuple(
                    np.repeat(x[None], K, axis=0) for x in (self._gs, self._gd))
                for x in self._constant_drive:
                    x.flags.writeable = False
            return self._constant_drive
        given = np.broadcast_to(moving[:, None], (self.n_rows, K))
        _, gs, gd = self._templates.update(np.ascontiguousarray(t.T), L.transpose(1, 0, 2),
                                           given)
        gs = np.where(given[..., None], gs, self._gs[:, None]).transpose(1, 0, 2)
        gd = np.where(given[..., None], gd, self._gd[:, None]).transpose(1, 0, 2)
        return gs, gd


_RENAMED = {"SpindleBank": "SpindleDriver"}  # renamed-from: the old names (spindle.renamed)


def __getattr__(name: str) -> object:
    return renamed_attribute(__name__, name, _RENAMED, globals())
