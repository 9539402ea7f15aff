"""The prosthesis chain over a leading axis of arms: every arm of a batch in one call per sample.

:class:`ArmChainBatch` is :class:`spindle.chain.arm.ArmChain` for ``n_arms`` independent
arms (a vector env's): each arm has its own median window, calibration stage, slew limit,
clamp, tracking low-pass, PI predictor (on its own update grid from its own reset time),
gamma drive, spindles, tendon organs (the force sense: load word, torque, tendon forces, Ib),
counters, handling of bad samples, gaps, bridges, restarts and clock
resyncs, exactly as the module docstring of :mod:`spindle.chain.arm` describes them. One
push gives every arm its own sample (or none: ``active``); arm k then equals a single
``ArmChain`` fed the same samples in the same order (same counters; same outputs to rounding,
the spindle step of many spindles runs in :mod:`spindle.batch_step` where one arm's runs on
floats).

Per-muscle arrays are (n_arms, 2) in :data:`~spindle.chain.config.MUSCLES` order; the
spindles are one :class:`~spindle.core.SpindleState` of 2 n_arms spindles, arm-major (arm i:
BRA 2i, TRImed 2i + 1), stepped by :func:`spindle.core.advance` once per sub-step for all
arms at once: with one step size when the arms share their sample times, else with each
arm's own (an encoder's jittered times); an arm whose interval has fewer sub-steps than
another's waits for its turn (its first steps are computed and not committed).

The common push (every arm active, its sample good, no restart) is recognised by four
reductions and runs without a loop over arms; rejected samples, restarts and resyncs are
handled with masks on the arms concerned. A push (and a whole block push) is atomic: if it
raises, every arm is left exactly as it was.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from spindle import core, number_rule, tendon_organ
from spindle.chain.conditioning import natural_rad_s, tracking_steps
from spindle.chain.config import (
    COUNTERS,
    MUSCLES,
    SCALAR_OUTPUTS,
    ArmSample,
    ChainConfig,
    real_array,
)
from spindle.chain.force import MomentArmFits, load_moment_arm_fits, tendon_forces_N
from spindle.chain.fusimotor import Fusimotor
from spindle.chain.length_model import LengthFits, load_length_fits
from spindle.chain.samples import BatchSample, lengths_valid
from spindle.chain.sensor import (
    MedianFilter,
    load_torque_Nm,
    valid_load_words,
    valid_readings,
)
from spindle.methods import get_method
from spindle.substeps import bounded_hermite_length, slew_limited

_COUNTER = {name: i for i, name in enumerate(COUNTERS)}
_OUTPUTS = tuple(f.name for f in fields(ArmSample) if f.name != "accepted")
_ALL = slice(None)
_MAX = np.maximum.reduce
LENGTH_RANGE_POINTS = 1301
"""Points of the angle grid over the fitted range on which each muscle's length range (the
fusimotor's h(x) and g(x) span) is taken; ``FIT_RANGE_POINTS`` in ``chain.c`` is the same."""


def fits_and_ranges(config: ChainConfig, fits: LengthFits | None
                    ) -> tuple[LengthFits, tuple[float, float], np.ndarray, np.ndarray]:
    """The chain's length fits (``fits``, or those of ``config.fits_path``), the angle range
    they hold (deg) and each muscle's shortest and longest length over it (L0): what the
    chain clamps to and spans h(x) with."""
    fits = fits if fits is not None else load_length_fits(config.fits_path)
    if fits.muscles != MUSCLES:
        raise ValueError(f"length fits are for {fits.muscles}, the chain needs {MUSCLES}")
    lo_rad, hi_rad = fits.valid_range_rad
    span = fits.length_L0(np.linspace(lo_rad, hi_rad, LENGTH_RANGE_POINTS))
    return fits, (math.degrees(lo_rad), math.degrees(hi_rad)), span.min(axis=0), span.max(axis=0)




@dataclass
class _Block:
    """A block push's samples once checked (:meth:`ArmChainBatch._block_samples`): times,
    values (each arm's accepted ones first), the accepted mask ``ok`` and intervals ``dt``
    (n, k), accepted counts ``n_ok`` and rejected counts (None: none) per arm, the
    counts of slew-limited and clamped samples the length stage adds, and the load words
    (n, k) (None: the samples carry no load reading)."""

    t: np.ndarray
    x: np.ndarray
    ok: np.ndarray
    dt: np.ndarray
    n_ok: np.ndarray
    rejected: np.ndarray | None
    slewed: np.ndarray
    clamped: np.ndarray | None = None
    angle: np.ndarray | None = None
    load: np.ndarray | None = None
    invalid_load: np.ndarray | int = 0
    missing_load: np.ndarray | int = 0


class ArmChainBatch:
    """The streaming chain of ``n_arms`` independent arms (BRA and TRImed each), in numpy.

    Call :meth:`reset` once (every arm), then push one sample per arm per call, each arm's
    samples in increasing time. Arm k behaves exactly as a single
    :class:`~spindle.chain.arm.ArmChain` with the same config and fits fed the same samples.

    Args:
        n_arms: number of arms (>= 1).
        config: :class:`~spindle.chain.config.ChainConfig` shared by every arm (its
            ``backend`` may not be ``"c"``: :func:`spindle.chain.make_batched_chain` builds
            the C batch).
        fits: the length fits (default: ``config.fits_path``'s).
        moment_arms: the moment-arm tables (default: ``config.moment_arm_fits_path``'s).
    """

    backend = "numpy"

    def __init__(self, n_arms: int, config: ChainConfig | None = None,
                 fits: LengthFits | None = None, moment_arms: MomentArmFits | None = None):
        if (isinstance(n_arms, bool | np.bool_) or not isinstance(n_arms, int | np.integer)
                or n_arms < 1):
            raise ValueError(f"n_arms={n_arms!r} must be an integer >= 1")
        self.n_arms = int(n_arms)
        config = ChainConfig() if config is None else config
        if config.backend == "c":
            raise ValueError(
                "ArmChainBatch is the numpy batch, but config.backend='c'; build the batch "
                "with spindle.chain.make_batched_chain(n_arms, config, fits)")
        self.config = replace(config, backend=self.backend)
        (self.fits, self.angle_range_deg, self.length_min_L0,
         self.length_max_L0) = fits_and_ranges(self.config, fits)
        self._theta = get_method(self.config.method).theta
        self._columns = core.columns(self.config.params)
        self._omega = (None if self.config.lowpass_hz is None
                       else natural_rad_s(self.config.lowpass_hz))
        n = self.n_arms
        self._median = MedianFilter(self.config.median_window, n)
        self._fusimotor = Fusimotor(self.length_min_L0, self.length_max_L0,
                                    self.config.fusimotor, n)
        self._ready = np.zeros(n, dtype=bool)  # reset at least once
        self._intended = np.full((n, 2), math.nan)  # NaN rows: the measured motion
        self._following = True  # every row of _intended NaN
        self._minus_one = np.full(n, -1.0)
        self._minus_one.flags.writeable = False
        self._counters = np.zeros((n, len(COUNTERS)), dtype=np.int64)
        self._behind = np.zeros(n, dtype=np.int64)  # samples older than the last accepted
        self._no_behind = self._behind  # (arrays are rebound, never written: one zero array)
        self._t = np.zeros(n)
        self._angle = np.zeros(n)
        self._u = np.ones((n, 2))  # the last accepted lengths (the low-pass's input)
        self._x = np.ones((n, 2))
        self._v = np.zeros((n, 2))
        self._a = np.zeros((n, 2))
        self._state = core.equilibrium_state(np.ones(2 * n), 0.0, 0.0, self.config.params)
        self.moment_arms = check_moment_arms(
            moment_arms if moment_arms is not None
            else load_moment_arm_fits(self.config.moment_arm_fits_path))
        # the tendon organs: 2 n_arms, arm-major as the spindles; rebound, never written into
        self._force_scale = np.tile(self.config.force_scale_N, n)
        self._gto_c = tendon_organ.state_space(self.config.gto)[2]
        self._gto = tendon_organ.equilibrium_state(np.zeros(2 * n), self._force_scale,
                                                   self.config.gto, 2 * n)
        self._torque = np.zeros(n)  # the last accepted sample's torque (held over bad words)
        self._out = _read_only({name: np.full(n if name in SCALAR_OUTPUTS else (n, 2), math.nan)
                                for name in _OUTPUTS})

    # -- state ---------------------------------------------------------------------------
    @property
    def counters(self) -> dict[str, np.ndarray]:
        """Each counter of :data:`~spindle.chain.config.COUNTERS`, (n_arms,) int64 (copies)."""
        return {name: self._counters[:, i].copy() for name, i in _COUNTER.items()}

    @property
    def last(self) -> BatchSample:
        """Every arm's latest output (``accepted`` True: the output of its last accepted
        sample or reset, as :attr:`ArmChain.last`)."""
        if not self._ready.all():
            raise RuntimeError(f"call ArmChainBatch.reset for every arm before using the "
                               f"chain (arms {np.flatnonzero(~self._ready).tolist()} never were)")
        return self._sample(np.ones(self.n_arms, dtype=bool))

    @property
    def spindle_state(self) -> core.SpindleState:
        """A copy of the spindles' state: 2 n_arms spindles, arm i's BRA 2i, TRImed 2i + 1."""
        return self._state.copy()

    @property
    def tendon_organ_state(self) -> tendon_organ.TendonOrganState:
        """A copy of the tendon organs' state: 2 n_arms organs, arm-major as the spindles."""
        return self._gto.copy()

    def reset(self, angle_deg: np.ndarray, t_s: float | np.ndarray = 0.0,
              length_L0: np.ndarray | None = None,
              arms: np.ndarray | None = None, load: np.ndarray | None = None) -> BatchSample:
        """Arms at rest at ``angle_deg`` (and, if given, exact ``length_L0``) at ``t_s``.

        ``arms`` None: every arm, ``angle_deg`` (n_arms,), ``t_s`` a scalar or (n_arms,),
        ``length_L0`` None or (n_arms, 2). ``arms`` an index array (m,): only those arms
        (the others are untouched), the values then (m,), (m,) and (m, 2). Each reset arm is
        :meth:`ArmChain.reset`: filters on its angle, template on its lengths, spindles at
        equilibrium, tendon organs at rest at the force of ``load`` ((m,) load words; None:
        no load, zero torque; an invalid word: zero torque, counted ``invalid_load``),
        counters at zero (``angle_clamped`` counts a clamped angle), the switch back to the
        measured motion. Bad values raise ``ValueError`` naming the arm; nothing
        changes then. Returns every arm's output (``accepted`` True for the reset arms).
        """
        rows = self._arms_index(arms)
        m = rows.size
        angle = self._per_arm("angle_deg", angle_deg, (m,), rows)
        t = np.broadcast_to(real_array(t_s), (m,)) if np.ndim(t_s) == 0 else \
            self._per_arm("t_s", t_s, (m,), rows)
        _check_finite("t_s", t, rows)
        _check_finite("angle_deg", angle, rows)
        if length_L0 is None:
            clamped, recorded = _clamped_angles(angle, self.angle_range_deg)
            L = self.fits.length_L0(np.radians(recorded))
        else:
            clamped = np.zeros(m, dtype=bool)
            recorded = angle.copy()
            L = self._per_arm("length_L0", length_L0, (m, 2), rows)
            bad = ~lengths_valid(L)
            if bad.any():
                i = int(np.argmax(bad))
                raise ValueError(f"length_L0 of arm {int(rows[i])} is {L[i]!r}; it must be 2 "
                                 f"finite lengths within {core.LENGTH_RANGE_L0} L0")
        if load is None:
            torque, bad_load = np.zeros(m), np.zeros(m, dtype=bool)
        else:
            torque, valid = self._load_torques(self._per_arm("load", load, (m,), rows),
                                               np.zeros(m))
            bad_load = ~valid
        saved = self._snapshot()
        try:
            self._intended = self._intended.copy()
            self._intended[rows] = math.nan
            self._following = bool(np.isnan(self._intended).all())
            minus_one = np.full(m, -1.0)
            self._rest(rows, np.array(t, dtype=float), recorded, L, self._rest_reading(angle),
                       minus_one, minus_one, torque)
            counters = self._counters.copy()
            counters[rows] = 0
            counters[rows, _COUNTER["angle_clamped"]] = clamped
            counters[rows, _COUNTER["invalid_load"]] = bad_load
            self._counters = counters
            ready = self._ready.copy()
            ready[rows] = True
            self._ready = ready
        except BaseException:
            self._restore(saved)
            raise
        accepted = np.zeros(self.n_arms, dtype=bool)
        accepted[rows] = True
        return self._sample(accepted)

    def set_intended_angle(self, angle_deg: np.ndarray | None) -> None:
        """The switch of every arm: drive its template from an intended elbow angle (deg).

        ``None``: every arm follows its measured motion; else (n_arms,), NaN for an arm that
        follows its measured motion. An angle outside the length model's range is clamped to
        it; an infinite one raises ``ValueError``. Holds until changed.
        """
        n = self.n_arms
        if angle_deg is None:
            self._intended = np.full((n, 2), math.nan)
            self._following = True
            return
        angle = self._per_arm("angle_deg", number_rule.real_array("angle_deg", angle_deg), (n,),
                              np.arange(n))
        if np.isinf(angle).any():
            i = int(np.argmax(np.isinf(angle)))
            raise ValueError(f"angle_deg of arm {i} is {angle[i]!r}; it must be a finite real "
                             "number (NaN: the measured motion)")
        given = ~np.isnan(angle)
        intended = np.full((n, 2), math.nan)
        if given.any():
            _, clamped = _clamped_angles(angle[given], self.angle_range_deg)
            intended[given] = self.fits.length_L0(np.radians(clamped))
        self._intended = intended
        self._following = not given.any()

    # -- pushes ----------------------------------------------------------------------------
    def push_counts(self, t_s: np.ndarray, counts: np.ndarray,
                    active: np.ndarray | None = None,
                    load: np.ndarray | None = None) -> BatchSample:
        """One encoder reading per arm: ``counts`` (n_arms,) taken at ``t_s`` (n_arms,), with
        the servo's load word ``load`` (n_arms,) read beside it (None: no load reading; the
        load rules of :mod:`spindle.chain.arm`).

        ``active`` (n_arms,) bool, None for all: an inactive arm gets no sample (state and
        counters untouched; its output repeats its last, ``accepted`` False).
        """
        return self._push("counts", t_s, counts, active, (), load=load)

    def push_angle(self, t_s: np.ndarray, angle_deg: np.ndarray,
                   active: np.ndarray | None = None) -> BatchSample:
        """One clean elbow angle (deg) per arm, (n_arms,), skipping the sensor stage."""
        return self._push("angle_deg", t_s, angle_deg, active, ())

    def push_lengths(self, t_s: np.ndarray, length_L0: np.ndarray,
                     active: np.ndarray | None = None,
                     angle_deg: np.ndarray | None = None) -> BatchSample:
        """The two fibre lengths (L0) of every arm, (n_arms, 2), skipping the sensor and the
        length model. ``angle_deg`` (n_arms,) is only recorded in the output (the arm's last
        angle where None or not finite)."""
        return self._push("length_L0", t_s, length_L0, active, (2,), angle_deg)

    def push_counts_block(self, t_s: np.ndarray, counts: np.ndarray,
                          n_samples: np.ndarray | None = None,
                          load: np.ndarray | None = None) -> BatchSample:
        """Arm i pushes its readings ``counts[i, :n_samples[i]]`` taken at ``t_s[i, ...]``
        (with load words ``load[i, ...]``, None: no load readings).

        ``t_s``, ``counts`` and ``load`` are (n_arms, k); ``n_samples`` (n_arms,) integers in 0..k
        (None: k each), entries past it are padding and ignored. Exactly
        :meth:`push_counts` column by column; atomic as a whole. Returns each arm's last
        output (as :meth:`ArmChain.push_counts_block`; an arm with no sample repeats its
        last with ``accepted`` False).
        """
        return self._block("counts", t_s, counts, n_samples, (), load=load)

    def push_angle_block(self, t_s: np.ndarray, angle_deg: np.ndarray,
                         n_samples: np.ndarray | None = None) -> BatchSample:
        """:meth:`push_angle` over (n_arms, k) times and angles; see
        :meth:`push_counts_block`."""
        return self._block("angle_deg", t_s, angle_deg, n_samples, ())

    def push_lengths_block(self, t_s: np.ndarray, length_L0: np.ndarray,
                           n_samples: np.ndarray | None = None,
                           angle_deg: np.ndarray | None = None) -> BatchSample:
        """:meth:`push_lengths` over (n_arms, k) times and (n_arms, k, 2) lengths (and
        recorded angles (n_arms, k)); see :meth:`push_counts_block`."""
        return self._block("length_L0", t_s, length_L0, n_samples, (2,), angle_deg)

    # -- the push --------------------------------------------------------------------------
    def _push(self, kind: str, t_s, signal, active, sample_shape, angle_deg=None, load=None
              ) -> BatchSample:
        n = self.n_arms
        t = _shaped("t_s", t_s, (n,), "(n_arms,)")
        x = _shaped(kind, signal, (n, *sample_shape), f"(n_arms{', 2' if sample_shape else ''})")
        count = np.ones(n, dtype=np.int64)
        if active is not None:
            active = np.asarray(active)
            if active.shape != (n,) or active.dtype != bool:
                raise ValueError(f"active has shape {active.shape} and dtype {active.dtype}; "
                                 f"expected ({n},) bool")
            count = active.astype(np.int64)
        angle = None if angle_deg is None else _shaped("angle_deg", angle_deg, (n,), "(n_arms,)")
        words = None if load is None else _shaped("load", load, (n,), "(n_arms,)")[:, None]
        return self._sample(self._run(kind, t[:, None], x[:, None], count,
                                      None if angle is None else angle[:, None], words))

    def _block(self, kind: str, t_s, signal, n_samples, sample_shape, angle_deg=None,
               load=None) -> BatchSample:
        n = self.n_arms
        t = np.array(real_array(t_s), dtype=float)  # a copy: the chain keeps its columns
        if t.ndim != 2 or t.shape[0] != n:
            raise ValueError(f"t_s has shape {t.shape}; expected ({n}, k) (n_arms, k)")
        k = t.shape[1]
        x = _shaped(kind, signal, (n, k, *sample_shape),
                    f"(n_arms, k{', 2' if sample_shape else ''}) like t_s")
        if n_samples is None:
            count = np.full(n, k)
        else:
            count = np.asarray(n_samples)
            if (count.shape != (n,) or count.dtype == bool
                    or not np.issubdtype(count.dtype, np.integer)):
                raise ValueError(f"n_samples has shape {count.shape} and dtype {count.dtype}; "
                                 f"expected ({n},) integers")
            if count.size and (count.min() < 0 or count.max() > k):
                raise ValueError(f"n_samples must lie in 0..{k} (the block's k), got "
                                 f"{count.min()}..{count.max()}")
        angle = None if angle_deg is None else _shaped("angle_deg", angle_deg, t.shape,
                                                       "(n_arms, k) like t_s")
        words = None if load is None else _shaped("load", load, t.shape, "(n_arms, k) like t_s")
        self._run(kind, t, x, count, angle, words)
        return self._sample(count > 0)

    def _run(self, kind: str, t: np.ndarray, x: np.ndarray, count: np.ndarray,
             angle: np.ndarray | None = None, load: np.ndarray | None = None) -> np.ndarray:
        """Arm i's samples ``x[i, :count[i]]`` at ``t[i, ...]`` (n, k) (and recorded angles,
        for lengths), atomically: in one pass (:meth:`_advance`) when the block holds only the
        common case, else column by column (:meth:`_column`). Returns which arms accepted a
        sample."""
        self._check_ready(None if count.min() > 0 else count > 0)
        if t.shape[1] == 0:
            return np.zeros(self.n_arms, dtype=bool)
        saved = self._snapshot()
        try:
            block = self._block_samples(kind, t, x, count, angle, load)
            if block is not None:
                self._advance(kind, block)
                return block.n_ok > 0
            accepted = np.zeros(self.n_arms, dtype=bool)
            for j in range(int(count.max())):
                accepted |= self._column(kind, t[:, j], x[:, j], count > j,
                                         None if angle is None else angle[:, j],
                                         None if load is None else load[:, j])
        except BaseException:
            self._restore(saved)
            raise
        return accepted

    def _advance(self, kind: str, block: _Block) -> None:
        """A checked block (:meth:`_block_samples`: every arm's given times increasing from
        its last accepted one by at most ``max_bridge_s``, no restart, no resync) in one pass:
        every rule but the time rules and restarts (:meth:`_column`) is applied here, for
        k columns (a block) or one (a push, or the arms of a column that continue).

        Everything that does not depend on the spindles (sensor stage, length fits, slew and
        range checks, the tracking filter's recursion, the PI predictor, the gamma drive and
        the sub-step lengths) is computed for all columns at once; the loop over columns
        then only steps and commits the spindles (arms without a sample in a column are
        stepped and not committed, like a waiting arm)."""
        angle, L, filtered, windows = self._block_lengths(kind, block)
        # -- the block is the common case: from here on the state changes --------------------
        ok, dt = block.ok, block.dt
        with np.errstate(all="ignore"):
            if self._omega is None:
                x1 = L
                v1 = (x1 - np.concatenate((self._x[:, None], x1[:, :-1]), axis=1)) / dt[..., None]
                a1 = (v1 - np.concatenate((self._v[:, None], v1[:, :-1]), axis=1)) / dt[..., None]
            else:
                x1, v1, a1 = tracking_steps(self._x, self._v,
                                            np.concatenate((self._u[:, None], L), axis=1),
                                            dt[..., None], self._omega)
        x0 = np.concatenate((self._x[:, None], x1[:, :-1]), axis=1)
        v0 = np.concatenate((self._v[:, None], v1[:, :-1]), axis=1)
        if self._following:
            template_in = x1
        else:
            template_in = np.where(np.isnan(self._intended[:, None]), x1,
                                   self._intended[:, None])
        t = np.where(ok, block.t, self._t[:, None])  # (padding: finite templates)
        template, gs, gd = self._fusimotor.update(t, template_in, ok)
        if kind == "counts":
            self._median.restore(windows)
        self._advance_block(ok, dt, x0, v0, x1, v1, gd, gs)
        torque, force, ib = self._advance_tendon_organs(kind, block, angle)
        self._count_block(kind, block)
        # -- each arm's last accepted sample: its state and outputs ----------------------------
        n, has = t.shape[0], block.n_ok > 0
        self._behind = self._no_behind if has.all() else np.where(has, 0, self._behind)
        r, last = np.arange(n), np.maximum(block.n_ok - 1, 0)
        ia, ii = core.afferents_from_tension(self._state.tension_FU.T, self._state.length_L0,
                                             self._columns)
        ia, ii = ia.reshape(-1, 2), ii.reshape(-1, 2)
        if kind == "counts":
            counts, filtered = block.x[r, last], filtered[r, last]
        else:
            counts = filtered = self._no_reading(n)
        values = dict(t=t[r, last], angle=angle[r, last], u=L[r, last], x=x1[r, last],
                      v=v1[r, last], a=a1[r, last], torque=torque[r, last])
        out = (values["t"], counts, filtered, values["angle"], values["torque"], values["x"],
               values["v"], values["a"], template[r, last], gs[r, last], gd[r, last], ia, ii,
               force[r, last], ib)
        if has.all():
            self._set(_ALL, **values)
            self._set_out(_ALL, *out)
        else:
            S = np.flatnonzero(has)
            self._set(S, **{name: value[S] for name, value in values.items()})
            self._set_out(S, *(value[S] for value in out))

    def _block_samples(self, kind: str, t: np.ndarray, x: np.ndarray, count: np.ndarray,
                       angle: np.ndarray | None = None, load: np.ndarray | None = None
                       ) -> _Block | None:
        """The block's samples checked for the common case (None if it is not: a time not
        after the arm's last accepted one, or an interval beyond ``max_bridge_s``), each
        arm's accepted samples moved first, in order; nothing changed."""
        cfg = self.config
        k = t.shape[1]
        cols = np.arange(k)
        given = cols < count[:, None]
        with np.errstate(invalid="ignore"):
            rise = np.diff(t, axis=1, prepend=self._t[:, None])
            if not bool(np.where(given, rise, 1.0).min() > 0.0):  # (NaN fails)
                return None
            valid = _valid_samples(kind, x, cfg.encoder.max_count)
        ok = given & valid
        rejected = given & ~valid
        any_rejected = bool(rejected.any())
        n_ok = ok.sum(axis=1) if any_rejected else count
        if any_rejected:  # each arm's accepted samples first, in order
            order = np.argsort(~ok, axis=1, kind="stable")
            t = np.take_along_axis(t, order, axis=1)
            x = np.take_along_axis(x, order if x.ndim == 2 else order[..., None], axis=1)
            if angle is not None:
                angle = np.take_along_axis(angle, order, axis=1)
            if load is not None:
                load = np.take_along_axis(load, order, axis=1)
            ok = cols < n_ok[:, None]
        with np.errstate(invalid="ignore"):
            dt = np.diff(t, axis=1, prepend=self._t[:, None])
        if not bool(np.where(ok, dt, 0.0).max() <= cfg.max_bridge_s):
            return None
        dt = np.where(ok, dt, cfg.spindle_step_s)  # (padding: any valid interval)
        return _Block(t=t, x=x, ok=ok, dt=dt, n_ok=n_ok, angle=angle, load=load,
                      rejected=rejected.sum(axis=1) if any_rejected else None,
                      slewed=np.zeros(t.shape[0], dtype=np.int64))

    def _block_lengths(self, kind: str, block: _Block):
        """(angle deg, lengths L0, filtered readings, median windows) of every column of a
        checked block: the sensor stage, the angle's slew limit and range, the length fits and
        the lengths' slew limit (their counts into ``block``); the median windows are only
        computed (:meth:`_fast_block` stores them once the block is known to go through)."""
        cfg = self.config
        ok, dt, x = block.ok, block.dt, block.x
        okm = ok[..., None]
        filtered = windows = None
        if kind == "length_L0":
            L = np.where(okm, x, self._u[:, None])
            angle = _held_values(block.angle, ok, self._angle)
        else:
            if kind == "counts":
                filtered, windows = self._median.filter(x, block.n_ok)
                angle = cfg.calibration.angle_deg(filtered)
            else:
                angle = x
            angle = np.where(ok, angle, self._angle[:, None])
            outside, bounded = _clamped_angles(angle, self.angle_range_deg)
            before = np.concatenate((self._angle[:, None], bounded[:, :-1]), axis=1)
            limit = cfg.max_speed_deg_s * dt
            if bool((ok & (np.abs(angle - before) > limit)).any()):
                # the slew limit reached: each column's limit depends on the last
                angle, slewed = _slew_angles(angle, limit, ok, self._angle,
                                             self.angle_range_deg)
                block.slewed += slewed.sum(axis=1)
                outside, bounded = _clamped_angles(angle, self.angle_range_deg)
            if bool(outside.any()):  # (padding: the last angle, inside)
                block.clamped = outside.sum(axis=1)
            angle = bounded
            L = self.fits.length_L0(np.radians(angle))
        u0 = np.concatenate((self._u[:, None], L[:, :-1]), axis=1)
        limit = cfg.max_speed_L0_s * dt[..., None]
        if bool((okm & (np.abs(L - u0) > limit)).any()):
            L, slewed = slew_limited(L, self._u, limit, axis=1)
            block.slewed += (ok & slewed.any(axis=2)).sum(axis=1)
        return angle, L, filtered, windows

    def _count_block(self, kind: str, block: _Block) -> None:
        """The counters of a block that went through."""
        counters = self._counters.copy()
        counters[:, _COUNTER["accepted"]] += block.n_ok
        counters[:, _COUNTER["gaps"]] += (block.ok & (block.dt > self.config.gap_s)).sum(axis=1)
        if block.rejected is not None:
            counters[:, _COUNTER[_INVALID[kind]]] += block.rejected
        if block.clamped is not None:
            counters[:, _COUNTER["angle_clamped"]] += block.clamped
        counters[:, _COUNTER["slew_limited"]] += block.slewed
        counters[:, _COUNTER["invalid_load"]] += block.invalid_load
        counters[:, _COUNTER["missing_load"]] += block.missing_load
        self._counters = counters

    def _load_torques(self, load: np.ndarray, held: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """(torque N m, validity) of load words (any shape): a valid word's torque, ``held``
        (broadcast) where the word is invalid."""
        valid = valid_load_words(load)
        torque = load_torque_Nm(np.where(valid, load, 0.0), self.config.load,
                                self.config.calibration.sign)
        return np.where(valid, torque, held), valid

    def _block_torques(self, kind: str, block: _Block) -> np.ndarray:
        """The torque (N m) of every column of a checked block (the load rules: a valid
        word's torque, the one before held over an invalid word, 0 without a load reading),
        their counts into ``block``."""
        ok = block.ok
        if block.load is None:
            if kind == "counts":
                block.missing_load = block.n_ok
            return np.zeros(ok.shape)
        torque, valid = self._load_torques(block.load, math.nan)
        block.invalid_load = (ok & ~valid).sum(axis=1)
        return _held_values(torque, ok, self._torque)

    def _advance_tendon_organs(self, kind: str, block: _Block, angle: np.ndarray
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The tendon organs of every arm through a block's accepted columns: the torque of
        each sample split into BRA and TRImed tendon forces at its conditioned angle, each
        organ stepped exactly over each interval (one step, the force a line between the
        samples: :func:`spindle.tendon_organ.step`). Returns the torques (n, k), forces
        (n, k, 2) and every arm's Ib after its last accepted column (n, 2)."""
        ok, n = block.ok, block.ok.shape[0]
        torque = self._block_torques(kind, block)
        force = tendon_forces_N(torque, np.radians(angle), self.moment_arms, clip=True)
        state, params = self._gto, self.config.gto
        if not (force.any() or state.z.any() or state.r_pps.any()):
            # at rest at zero force, and staying there (no load, or none yet): the steps
            # would give exact zeros
            return torque, force, np.zeros((n, 2))
        for j in range(ok.shape[1]):
            live = np.repeat(ok[:, j], 2)
            if not live.any():
                break
            new = state.copy()
            tendon_organ.step(new, force[:, j].reshape(-1), self._force_scale,
                              tendon_organ.plan_steps(params, np.repeat(block.dt[:, j], 2)))
            if not live.all():
                for name in ("z", "force_N", "r_pps"):
                    setattr(new, name, np.where(live, getattr(new, name),
                                                getattr(state, name)))
            state = new
        self._gto = state
        ib = tendon_organ.rate_pps(state, self._gto_c).reshape(n, 2)
        return torque, force, ib

    def _advance_block(self, ok, dt, x0, v0, x1, v1, gd, gs) -> None:
        """The spindles of every arm through a block's accepted columns ``ok`` (n, k): the
        sub-step lengths of all columns at once (:meth:`_advance_group`'s curve and limits),
        then one :func:`core.advance` per sub-step for all arms."""
        n, k = ok.shape
        step_s = self.config.spindle_step_s
        counts = np.maximum(np.ceil(dt / step_s * (1 - 1e-12)), 1.0)
        h = dt / counts
        steps = int(_MAX(counts, axis=None))
        reach = (self.config.max_speed_L0_s * h)[..., None]
        counts_m, dt_m = counts[..., None], dt[..., None]
        first = steps - counts_m  # each arm's sub-steps start this late (it waits before)
        # sub-step lengths (steps, n, k, 2); arms that wait keep x0 (not committed)
        lengths = np.empty((steps, n, k, 2))
        lengths[-1] = x1
        previous = x0
        with np.errstate(all="ignore"):
            for q in range(1, steps):
                own = np.maximum(q - first, 0.0)
                Ls = bounded_hermite_length(own / counts_m, x0, x1, v0, v1, dt_m, previous,
                                            reach, reach * (counts_m - own))
                previous = lengths[q - 1] = np.where(own > 0.0, Ls, x0)
        # column-major for the loop: (k, steps, 2n) lengths, (k, 2n) drive and moving masks
        lengths = np.ascontiguousarray(lengths.transpose(2, 0, 1, 3)).reshape(k, steps, 2 * n)
        gd_cols = np.ascontiguousarray(gd.transpose(1, 0, 2)).reshape(k, 2 * n)
        gs_cols = np.ascontiguousarray(gs.transpose(1, 0, 2)).reshape(k, 2 * n)
        start = np.repeat((steps - counts).T.astype(np.int64), 2, axis=1)  # (k, 2n)
        live = np.repeat(ok.T, 2, axis=1)
        h_ok = np.where(ok, h, math.nan)
        h_lo, h_hi = np.fmin.reduce(h_ok, axis=0), np.fmax.reduce(h_ok, axis=0)
        h_spindles = np.repeat(np.where(ok, h, h_hi).T, 2, axis=1)
        state, theta, c = self._state, self._theta, self._columns
        for j in range(k):
            if not live[j].any():
                break
            h_j = float(h_lo[j]) if h_lo[j] == h_hi[j] else h_spindles[j]
            all_live = bool(live[j].all())
            gd_j, gs_j = gd_cols[j], gs_cols[j]
            for q in range(int(start[j].min()), steps):
                L_q = lengths[j, q]
                new = core.advance(state, L_q, gd_j, gs_j, h_j, theta, c)
                if all_live and q >= start[j].max():
                    core.commit(state, new, L_q, gd_j, gs_j)
                else:
                    core.commit(state, new, L_q, gd_j, gs_j, where=live[j] & (start[j] <= q))

    def _column(self, kind: str, t: np.ndarray, x: np.ndarray, active: np.ndarray,
                angle: np.ndarray | None = None, load: np.ndarray | None = None) -> np.ndarray:
        """One sample per active arm, whatever its time: the time rules (repeated,
        backwards, bad, clock resyncs), the validity rules, restarts; the arms that continue
        then go through :meth:`_advance` as a block of one column. Returns the accepted mask.

        Rebinds the chain's arrays (never writes into them) except the median windows, the
        predictors and the spindles, which the caller's snapshot covers."""
        cfg = self.config
        counters = self._counters.copy()
        with np.errstate(invalid="ignore"):  # inf - inf where a time is not finite
            dt = t - self._t
        given = active & np.isfinite(t)
        counters[:, _COUNTER["bad_time"]] += active & ~np.isfinite(t)
        counters[:, _COUNTER["repeated_time"]] += given & (dt == 0.0)
        back = given & (dt < 0.0)
        behind = self._behind + back
        time_ok = (given & (dt > 0.0)) | (back & (behind >= cfg.resync_after_samples))
        counters[:, _COUNTER["time_backwards"]] += back & ~time_ok
        valid = _valid_samples(kind, x, cfg.encoder.max_count)
        counters[:, _COUNTER[_INVALID[kind]]] += time_ok & ~valid
        ok = time_ok & valid
        # an accepted sample starts the count of late ones anew
        self._behind = np.where(ok, 0, behind)
        restart = ok & ((dt < 0.0) | (dt > cfg.max_bridge_s))
        if restart.any():
            self._restart(kind, np.flatnonzero(restart), t, x, dt, counters, angle, load)
        self._counters = counters
        going = ok & ~restart
        if going.any():
            self._advance(kind, self._block_samples(
                kind, t[:, None], x[:, None], going.astype(np.int64),
                None if angle is None else angle[:, None],
                None if load is None else load[:, None]))
        return ok

    def _restart(self, kind: str, rows: np.ndarray, t: np.ndarray, x: np.ndarray,
                 dt: np.ndarray, counters: np.ndarray, angle: np.ndarray | None,
                 load: np.ndarray | None) -> None:
        """Arms ``rows`` restart at rest at their new sample (an interval beyond
        ``max_bridge_s``, or a clock resync), counted: as :meth:`reset` at its angle (the
        median window on its own reading, clamped to the length model's range; the tendon
        organs at rest at its force, by the load rules) but keeping the counters and the
        switch."""
        x, t, dt = x[rows], t[rows], dt[rows]
        if load is None:
            torque = np.zeros(rows.size)
            if kind == "counts":
                counters[rows, _COUNTER["missing_load"]] += 1
        else:
            torque, valid = self._load_torques(load[rows], self._torque[rows])
            counters[rows, _COUNTER["invalid_load"]] += ~valid
        none = np.full(rows.size, -1.0)
        if kind == "length_L0":
            angle = _held_values(None if angle is None else angle[rows, None],
                                     np.ones((rows.size, 1), dtype=bool), self._angle[rows])[:, 0]
            L, counts, filtered = x, none, none
            reading = self._rest_reading(angle)
        else:
            if kind == "counts":
                counts = filtered = reading = x
                given = self.config.calibration.angle_deg(x)
            else:
                given, counts, filtered = x, none, none
                reading = self._rest_reading(given)
            clamped, angle = _clamped_angles(given, self.angle_range_deg)
            counters[rows, _COUNTER["angle_clamped"]] += clamped
            L = self.fits.length_L0(np.radians(angle))
        counters[rows, _COUNTER["restarts"]] += 1
        counters[rows, _COUNTER["clock_resyncs"]] += dt < 0.0
        counters[rows, _COUNTER["accepted"]] += 1
        counters[rows, _COUNTER["gaps"]] += dt > self.config.gap_s
        self._rest(rows, t, angle, L, reading, counts, filtered, torque)

    def _no_reading(self, m: int) -> np.ndarray:
        # the outputs share one read-only array of -1 (no encoder reading)
        return self._minus_one if m == self.n_arms else np.full(m, -1.0)

    def _rest(self, rows, t, angle, L, reading, counts, filtered, torque) -> None:
        """Arms ``rows`` at rest (``ArmChain._rest``): what reset and a restart share; the
        tendon organs at rest at the force of ``torque`` (N m) at ``angle``."""
        intended = self._intended[rows]
        template_in = np.where(np.isnan(intended), L, intended)
        template, gs, gd = self._fusimotor.reset(t, template_in, rows)
        state = core.equilibrium_state(L.reshape(-1), gd.reshape(-1), gs.reshape(-1),
                                       self.config.params)
        ia, ii = core.afferents(state, self.config.params)
        self._median.reset(reading, rows)
        _scatter(self._state, _spindles(rows), state)
        force = tendon_forces_N(torque, np.radians(angle), self.moment_arms, clip=True)
        organs = _spindles(rows)
        rest = tendon_organ.equilibrium_state(force.reshape(-1), self._force_scale[organs],
                                              self.config.gto, organs.size)
        gto = self._gto.copy()
        gto.z[:, organs], gto.force_N[organs], gto.r_pps[organs] = rest.z, rest.force_N, \
            rest.r_pps
        self._gto = gto
        ib = tendon_organ.rate_pps(rest, self._gto_c).reshape(-1, 2)
        zeros = np.zeros_like(L)
        self._set(rows, t=t, angle=angle, u=L, x=L, v=zeros, a=zeros, torque=torque)
        self._behind = self._behind.copy()
        self._behind[rows] = 0
        self._set_out(rows, t, counts, filtered, angle, torque, L, zeros, zeros, template, gs,
                      gd, ia.reshape(-1, 2), ii.reshape(-1, 2), force, ib)

    def _set(self, S, **values) -> None:
        for name, value in values.items():
            attr = "_" + name
            if S is _ALL:
                setattr(self, attr, value)
            else:
                new = getattr(self, attr).copy()
                new[S] = value
                setattr(self, attr, new)

    def _set_out(self, S, *values) -> None:
        if S is _ALL:
            self._out = _read_only(dict(zip(_OUTPUTS, values, strict=True)))
            return
        out = {}
        for name, value in zip(_OUTPUTS, values, strict=True):
            new = self._out[name].copy()
            new[S] = value
            out[name] = new
        self._out = _read_only(out)

    # -- helpers ---------------------------------------------------------------------------
    def _sample(self, accepted: np.ndarray) -> BatchSample:
        accepted.flags.writeable = False
        return BatchSample(accepted=accepted, **self._out)

    def _snapshot(self) -> tuple:
        # The chain's own arrays are rebound, never written into, so holding them is enough;
        # the median windows, predictors and spindles are written in place: copies.
        return (dict(self.__dict__), self._median.snapshot(),
                self._fusimotor.predictor.snapshot(),
                [getattr(self._state, name).copy() for name in core.STATE_FIELDS])

    def _restore(self, saved: tuple) -> None:
        attributes, median, predictor, spindles = saved
        self.__dict__.update(attributes)
        self._median.restore(median)
        self._fusimotor.predictor.restore(predictor)
        for name, array in zip(core.STATE_FIELDS, spindles, strict=True):
            getattr(self._state, name)[...] = array

    def _check_ready(self, active: np.ndarray | None) -> None:
        waiting = ~self._ready if active is None else active & ~self._ready
        if waiting.any():
            raise RuntimeError("call ArmChainBatch.reset before pushing samples (arms "
                               f"{np.flatnonzero(waiting).tolist()} were never reset)")

    def _arms_index(self, arms) -> np.ndarray:
        n = self.n_arms
        if arms is None:
            return np.arange(n)
        rows = np.asarray(arms)
        if rows.ndim != 1 or rows.dtype == bool or not (
                rows.size == 0 or np.issubdtype(rows.dtype, np.integer)):
            raise ValueError(f"arms has shape {rows.shape} and dtype {rows.dtype}; expected a "
                             "1-D array of arm indices")
        if rows.size and (rows.min() < 0 or rows.max() >= n):
            raise ValueError(f"arms holds {rows.min()}..{rows.max()}; arm indices lie in "
                             f"0..{n - 1}")
        if np.unique(rows).size != rows.size:
            raise ValueError(f"arms={rows.tolist()} names an arm twice")
        return rows.astype(np.intp)

    @staticmethod
    def _per_arm(name: str, value, shape: tuple[int, ...], rows: np.ndarray) -> np.ndarray:
        return _shaped(name, value, shape, "(m,) for m arms" if len(shape) == 1
                       else "(m, 2) for m arms")

    def _rest_reading(self, angle: np.ndarray) -> np.ndarray:
        # The reading at that angle, clamped to what an encoder can read: with exact lengths
        # the angle is only recorded and may lie anywhere.
        with np.errstate(over="ignore"):
            counts = self.config.calibration.counts(angle)
        return np.minimum(np.maximum(counts, 0.0), float(self.config.encoder.max_count))


def _shaped(name: str, value, shape: tuple[int, ...], meaning: str) -> np.ndarray:
    """``value`` as a float array (NaN for non-real entries) of exactly ``shape``."""
    array = np.array(real_array(value), dtype=float)  # a copy: the chain keeps its inputs
    if array.shape != shape:
        raise ValueError(f"{name} has shape {array.shape}; expected {shape} {meaning}")
    return array


def _check_finite(name: str, values: np.ndarray, rows: np.ndarray) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{name} of arm {int(rows[i])} is {values[i]!r}; it must be a finite "
                         "real number")


def _held_values(given: np.ndarray | None, ok: np.ndarray, last: np.ndarray
                 ) -> np.ndarray:
    """Values held over the missing ones (n, k): each accepted column's given value where it
    is finite, else the one before (from ``last`` (n,)). The angles recorded with lengths,
    the torques of load words."""
    n, k = ok.shape
    if given is None:
        return np.broadcast_to(last[:, None], (n, k))
    angles = np.concatenate((last[:, None], given), axis=1)
    known = np.concatenate((np.ones((n, 1), dtype=bool), ok & np.isfinite(given)), axis=1)
    source = np.maximum.accumulate(np.where(known, np.arange(k + 1), 0), axis=1)
    return np.take_along_axis(angles, source, axis=1)[:, 1:]


_INVALID = {"counts": "invalid_reading", "angle_deg": "invalid_angle",
            "length_L0": "invalid_length"}
"""The counter of each entry point's invalid samples."""


def check_moment_arms(moment_arms: MomentArmFits) -> MomentArmFits:
    """``moment_arms`` if they are BRA's and TRImed's, in that order, else ValueError."""
    if moment_arms.muscles != MUSCLES:
        raise ValueError(f"moment arms are for {moment_arms.muscles}, the chain needs {MUSCLES}")
    return moment_arms


def _valid_samples(kind: str, x: np.ndarray, max_count: int) -> np.ndarray:
    """Whether each sample of an entry point is valid (the validity rules of
    ``docs/faults.md``): a reading an integer in 0..max_count, an angle finite, the two
    lengths finite and within the spindle's range."""
    if kind == "counts":
        return valid_readings(x, max_count)
    if kind == "angle_deg":
        return np.isfinite(x)
    return lengths_valid(x)


def _clamped_angles(angle: np.ndarray, angle_range_deg: tuple[float, float]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The angle rule: an angle outside the length model's range is clamped to it. Returns
    where it acted and the clamped angles."""
    lo, hi = angle_range_deg
    return (angle < lo) | (angle > hi), np.minimum(np.maximum(angle, lo), hi)


def _slew_angles(angle, limit, ok, last, angle_range_deg) -> tuple[np.ndarray, np.ndarray]:
    """The angles' slew limit column by column over (n, k) angles (each column's last angle
    the previous one's, clamped to the range); returns the limited angles (before the clamp)
    and where the limit acted (on ``ok``)."""
    out = angle.copy()
    slewed = np.zeros(angle.shape, dtype=bool)
    for j in range(angle.shape[1]):
        change = angle[:, j] - last
        slew = ok[:, j] & (np.abs(change) > limit[:, j])
        out[:, j] = np.where(slew, last + np.copysign(limit[:, j], change), angle[:, j])
        slewed[:, j] = slew
        last = _clamped_angles(out[:, j], angle_range_deg)[1]
    return out, slewed




def _spindles(rows) -> np.ndarray:
    """The spindle indices (arm-major: BRA 2i, TRImed 2i + 1) of arms ``rows``."""
    rows = np.asarray(rows)
    return np.stack((2 * rows, 2 * rows + 1), axis=1).reshape(-1)




def _scatter(state: core.SpindleState, spindles: np.ndarray, part: core.SpindleState) -> None:
    """Write ``part`` into the spindles ``spindles`` of ``state``."""
    for name in core.STATE_FIELDS:
        target, source = getattr(state, name), getattr(part, name)
        if target.ndim == 2:
            target.T[:, spindles] = source.T
        else:
            target[spindles] = source


def _read_only(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    for array in arrays.values():
        array.flags.writeable = False
    return arrays
