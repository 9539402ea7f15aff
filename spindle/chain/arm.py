"""The seed paper's processing chain for one arm: encoder counts in, Ia and II out.

    counts -> median filter (7) -> f(x) -> elbow angle -> fitted BRA/TRImed fibre lengths
           -> tracking low-pass (L, dL/dt) -> PI template -> gamma_s = h, gamma_d = g
           -> Mileusnic spindles (HUMAN gains) -> Ia, II per muscle

This is what would run on the prosthesis, so it needs no MuJoCo. :class:`ArmChain` streams:
push samples as they come and read the rates. :func:`run_chain` takes a whole trace and
returns every intermediate signal; it is :class:`ArmChain` driven sample by sample, so the
two agree exactly.

Three entry points feed the same chain at different stages: encoder counts
(:meth:`ArmChain.push_counts`, the prosthesis), clean elbow angles (:meth:`~ArmChain.push_angle`,
skipping the sensor stage) and fibre lengths (:meth:`~ArmChain.push_lengths`, e.g. exact
lengths from MuJoCo, skipping the length model).

Handling rules for bad samples (all counted in :attr:`ArmChain.counters`; a rejected sample
changes no state and the previous output is returned again with ``accepted=False``):

- ``invalid_reading``: counts that are NaN, not an integer, or outside 0..max_count
  (the encoder's dropout code -1 and corrupted words): rejected. A corrupted word that happens
  to fall inside 0..max_count is a spike: the median filter removes it;
- ``invalid_angle`` / ``invalid_length``: a non-finite angle, or lengths that are non-finite,
  of the wrong shape or outside the spindle's range: rejected;
- ``repeated_time``, ``time_backwards``, ``bad_time``: a sample whose time equals, precedes or
  is not a finite number after the last accepted one: rejected (time never runs backwards);
- ``clock_resyncs``: the ``resync_after_samples``-th sample (default 7) since the last
  accepted one to come with an earlier time is not rejected: the chain takes the new clock as
  the true one and restarts at rest at that sample (also counted in ``restarts``). A single
  corrupt time far ahead, accepted as a long gap, would otherwise lock out every true sample
  after it;
- ``gaps``: an interval longer than ``max_gap_s`` (default: the filter window, 7 nominal
  sample periods) since the last accepted sample (dropped samples): accepted and counted. Up
  to ``max_bridge_s`` (default 50 ms) the gap is bridged: the median window keeps the last 7
  accepted readings, the low-pass filter is advanced exactly across the gap and the spindles
  follow a smooth (Hermite) curve between its states before and after;
- ``restarts``: an interval longer than ``max_bridge_s`` (a long dropout, or a clock that
  jumped, e.g. to 1e9 s) is not bridged: the chain restarts at rest at the new sample, exactly
  as :meth:`ArmChain.reset` at its angle (median window on its reading, low-pass at rest,
  predictor at rest, spindles at equilibrium) but keeping the counters and the switch; counted
  here and in ``gaps``. Every push therefore costs bounded work, whatever the times;
- ``slew_limited``: the conditioned angle may change by at most ``max_speed_deg_s`` times the
  interval (default 1000 deg/s, above the servo's 684 deg/s no-load speed), lengths by at most
  ``max_speed_L0_s`` times it; a faster change (a jump after a gap, a spike the median let
  through) is limited to that and counted;
- ``angle_clamped``: an angle outside the length model's range (0-130 deg) is clamped to it,
  the angle given to :meth:`ArmChain.reset` (so :func:`run_chain`'s first sample) included.

Values that are not one real number (complex numbers, integers too large for a float,
strings, ``None``) count as non-finite: a bad sample above, or ``ValueError`` from
:meth:`ArmChain.reset`. The spindles' sub-step lengths (the Hermite curve across each
interval) are kept within the spindle's range (0.5-1.5 L0), within ``max_speed_L0_s`` of the
previous sub-step and able to reach the new length at that speed, so a bridge never leaves
the valid range however the motion before it went. A push is atomic: if it raises (a spindle
step that fails), the chain, its counters included, is left exactly as it was.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from spindle import core
from spindle.derivatives import natural_rad_s, tracking_step
from spindle.fusimotor import SEED_PAPER, Fusimotor, FusimotorParams
from spindle.length_fits import LengthFits, load_length_fits
from spindle.methods import get_method
from spindle.params import HUMAN, SpindleParams
from spindle.sensor import AX12, Calibration, EncoderParams, MedianFilter, is_valid_reading
from spindle.simulate import hermite_weights

MUSCLES = ("BRA", "TRImed")
BACKENDS = ("numpy", "c")
"""``ChainConfig.backend``: ``"numpy"`` (this module) or ``"c"`` (``spindle/c/chain.c`` through
:mod:`spindle.cchain`, compiled on first use: same API, outputs and counters)."""

COUNTERS = (
    "accepted", "invalid_reading", "invalid_angle", "invalid_length", "repeated_time",
    "time_backwards", "bad_time", "gaps", "slew_limited", "angle_clamped", "restarts",
    "clock_resyncs",
)
"""Names of :attr:`ArmChain.counters` (see the module docstring for each rule)."""
MAX_RESYNC_AFTER_SAMPLES = 1_000_000
"""Largest ``ChainConfig.resync_after_samples`` (``PS_CHAIN_MAX_RESYNC`` in C: an int there)."""

MAX_BRIDGE_UPDATES = 100_000
"""Most spindle sub-steps or predictor updates one bridged interval may take
(``PS_CHAIN_MAX_BRIDGE_UPDATES`` in C, a tenth of the C chain's last-resort guard):
``ChainConfig`` refuses a ``max_bridge_s`` needing more, so the work of a push is bounded."""


@dataclass(frozen=True)
class ChainConfig:
    """Every setting of the chain (frozen; defaults: the seed paper's system).

    Attributes:
        encoder: the encoder's range and nominal rate (validity of readings, default gap).
        calibration: f(x), counts to elbow angle.
        median_window: the median filter's window (odd; paper: 7).
        lowpass_hz: natural frequency of the tracking low-pass on the lengths (Hz); ``None``
            passes lengths unfiltered (only for clean inputs). 20 Hz delays a movement by
            16 ms; it minimised the total Ia/II error of the encoder chain against the
            noise-free one among 5-50 Hz (``scripts/chain_figures.py``).
        fusimotor: :class:`~spindle.fusimotor.FusimotorParams`.
        params: spindle constants (default :data:`spindle.HUMAN`, G x 1/5).
        method: the spindle integrator (``"trapezoidal"``, ``"backward_euler"``,
            ``"forward_euler"``).
        step_s: largest internal spindle step (s); each sample interval is split into equal
            sub-steps no longer than it. ``None``: the method's default.
        max_gap_s: intervals longer than this are counted as gaps; ``None``: the median window
            times the nominal sample period (14 ms).
        max_bridge_s: the longest interval bridged by the smooth curve; a longer one restarts
            the chain at rest at the new sample (counter ``restarts``). The default, 50 ms
            (25 periods of the seed paper's 500 Hz encoder), is where extrapolating the motion
            before a gap stops meaning something: the velocity a bridge starts from predicts
            the arm for a fraction of a movement's cycle, and voluntary elbow movement and
            tremor stay below about 10 Hz (half a cycle: 50 ms); by then the 20 Hz low-pass
            (1/w = 8 ms) has long forgotten its state before the gap (e^(-wT)(1 + wT) = 1.4 %),
            and across 50 ms the Hermite curve between any two states the low-pass can reach
            stays within the 8 L0/s slew limit (measured; it exceeds the spindle's 10 L0/s
            from about 100 ms on, where the sub-step limits take over). It also bounds the
            work of a push: at most ``max_bridge_s / step_s`` spindle sub-steps (50).
        resync_after_samples: a sample older than the last accepted one is rejected
            (``time_backwards``), unless it is the ``resync_after_samples``-th such sample
            since the last accepted one: then the chain trusts the new clock and restarts at
            rest at that sample (counters ``restarts`` and ``clock_resyncs``). Without it, a
            single corrupt time far in the future, once accepted as a long gap, would make
            every later true sample "backwards" and the chain would never accept one again.
            The default, 7, is the median window: as many readings as the filter needs before
            it follows a change.
        max_speed_deg_s: slew limit of the conditioned angle (deg/s).
        max_speed_L0_s: slew limit of the lengths (L0/s), below the spindle's 10 L0/s.
        fits_path: length fits (``None``: the bundled ``models/length_fits.json``).
        backend: ``"numpy"`` or ``"c"`` (:data:`BACKENDS`); ``ArmChain(config)`` with
            ``backend="c"`` is a :class:`spindle.cchain.CArmChain`.
    """

    encoder: EncoderParams = AX12
    calibration: Calibration = field(default_factory=Calibration)
    median_window: int = 7
    lowpass_hz: float | None = 20.0
    fusimotor: FusimotorParams = SEED_PAPER
    params: SpindleParams = HUMAN
    method: str = "trapezoidal"
    step_s: float | None = None
    max_gap_s: float | None = None
    max_bridge_s: float = 0.05
    resync_after_samples: int = 7
    max_speed_deg_s: float = 1000.0
    max_speed_L0_s: float = 8.0
    fits_path: str | Path | None = None
    backend: str = "numpy"

    def __post_init__(self) -> None:
        # bool is an int and a float to Python; here it is always a mistake
        _check_positive_int("median_window", self.median_window)
        _check_positive_int("resync_after_samples", self.resync_after_samples,
                            MAX_RESYNC_AFTER_SAMPLES)
        if self.median_window % 2 == 0:
            raise ValueError(f"median_window={self.median_window!r} must be an odd integer >= 1")
        for name in ("lowpass_hz", "step_s", "max_gap_s"):
            if getattr(self, name) is not None:
                _check_positive_real(name, getattr(self, name))
        for name in ("max_bridge_s", "max_speed_deg_s", "max_speed_L0_s"):
            _check_positive_real(name, getattr(self, name))
        if self.lowpass_hz is not None:
            natural_rad_s(self.lowpass_hz)
        method = get_method(self.method)
        if self.step_s is not None:
            core.check_step(float(self.step_s), method)
        bridge = float(self.max_bridge_s)
        updates = max(bridge / self.spindle_step_s, bridge * self.fusimotor.predictor_rate_hz)
        if updates > MAX_BRIDGE_UPDATES:
            raise ValueError(
                f"max_bridge_s={self.max_bridge_s!r} needs {updates:.3g} spindle sub-steps or "
                f"predictor updates per push, above {MAX_BRIDGE_UPDATES}")
        if not float(self.max_speed_L0_s) <= core.MAX_SPEED_L0_S:
            raise ValueError(
                f"max_speed_L0_s={self.max_speed_L0_s!r} must lie in (0, "
                f"{core.MAX_SPEED_L0_S}] (the spindle's speed limit)"
            )
        if not isinstance(self.backend, str) or self.backend not in BACKENDS:
            raise ValueError(f"backend={self.backend!r} is not one of {BACKENDS}")

    @property
    def gap_s(self) -> float:
        if self.max_gap_s is not None:
            return float(self.max_gap_s)
        return self.median_window * self.encoder.period_s

    @property
    def spindle_step_s(self) -> float:
        m = get_method(self.method)
        return m.default_step_s if self.step_s is None else float(self.step_s)


@dataclass(frozen=True)
class ArmSample:
    """The chain's output after one sample; per-muscle arrays are (2,) in order BRA, TRImed.

    Attributes:
        t_s: sample time (s).
        accepted: False if this sample was rejected (every other field then repeats the
            previous output).
        counts: the raw reading (-1 when the sample did not come from the encoder).
        counts_filtered: the median-filtered reading (-1 likewise).
        angle_deg: conditioned elbow angle (deg).
        length_L0: conditioned (low-passed) fibre length.
        velocity_L0_s, acceleration_L0_s2: its first and second time derivatives.
        template_L0: the fusimotor template (PI predictor output).
        gamma_static_pps, gamma_dynamic_pps: fusimotor drive.
        ia_pps, ii_pps: primary and secondary afferent rates.
    """

    t_s: float
    accepted: bool
    counts: float
    counts_filtered: float
    angle_deg: float
    length_L0: np.ndarray
    velocity_L0_s: np.ndarray
    acceleration_L0_s2: np.ndarray
    template_L0: np.ndarray
    gamma_static_pps: np.ndarray
    gamma_dynamic_pps: np.ndarray
    ia_pps: np.ndarray
    ii_pps: np.ndarray


class ArmChain:
    """The streaming chain of one arm (BRA and TRImed).

    Call :meth:`reset` once, then push samples in increasing time. Each accepted push
    advances the spindles from the previous sample's time to the new one.

    With ``config.backend == "c"`` the constructor returns a
    :class:`spindle.cchain.CArmChain` (a subclass: the same API, computed in C), so the
    numpy path below carries no dispatch cost.
    """

    def __new__(cls, config: ChainConfig | None = None, fits: LengthFits | None = None,
                *args, **kwargs):
        if cls is ArmChain and config is not None and config.backend == "c":
            from spindle.cchain import CArmChain

            return super().__new__(CArmChain)
        return super().__new__(cls)

    def __init__(self, config: ChainConfig | None = None, fits: LengthFits | None = None):
        self.config = ChainConfig() if config is None else config
        self.fits = fits if fits is not None else load_length_fits(self.config.fits_path)
        if self.fits.muscles != MUSCLES:
            raise ValueError(f"length fits are for {self.fits.muscles}, the chain needs {MUSCLES}")
        lo_rad, hi_rad = self.fits.valid_range_rad
        self.angle_range_deg = (math.degrees(lo_rad), math.degrees(hi_rad))
        span = self.fits.length_L0(np.linspace(lo_rad, hi_rad, 1301))
        self.length_min_L0 = span.min(axis=0)
        self.length_max_L0 = span.max(axis=0)
        self._method = get_method(self.config.method)
        self._columns = core.columns(self.config.params)
        self._omega = (None if self.config.lowpass_hz is None
                       else natural_rad_s(self.config.lowpass_hz))
        self._median = MedianFilter(self.config.median_window)
        self._fusimotor = Fusimotor(self.length_min_L0, self.length_max_L0, self.config.fusimotor)
        self._intended_L0: np.ndarray | None = None
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._behind = 0  # samples older than the last accepted one, since it
        self._last: ArmSample | None = None

    # -- state ---------------------------------------------------------------------------
    def reset(self, angle_deg: float, t_s: float = 0.0,
              length_L0: np.ndarray | None = None) -> ArmSample:
        """The arm at rest at ``angle_deg`` (and, if given, exact ``length_L0``) at ``t_s``.

        Filters start on that angle, the template on those lengths, the spindles at
        equilibrium with the resulting drive. Counters restart at zero; without
        ``length_L0``, an angle outside the length model's range is clamped to it and counted
        (``angle_clamped``), as a pushed angle is. The switch returns to the measured motion.
        """
        t = _real(t_s)
        if not math.isfinite(t):
            raise ValueError(f"t_s={t_s!r} must be a finite real number")
        angle = self._check_angle(angle_deg)
        clamped = False
        if length_L0 is None:
            clamped, recorded = self._clamp_angle(angle)
            L = self.fits.length_L0(math.radians(recorded))
        else:
            recorded = angle
            L = self._check_lengths(length_L0)
            if L is None:
                raise ValueError(f"length_L0={length_L0!r} must be 2 finite lengths within "
                                 f"{core.LENGTH_RANGE_L0} L0")
        self._intended_L0 = None
        out = self._rest(t, recorded, L, self._rest_reading(angle), -1.0, -1.0)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.counters["angle_clamped"] = int(clamped)
        return out

    def set_intended_angle(self, angle_deg: float | None) -> None:
        """The switch: drive the fusimotor template from an intended elbow angle (deg).

        ``None`` returns to the measured motion. The intended angle holds until changed; call
        it before each push to follow an intended trajectory.
        """
        if angle_deg is None:
            self._intended_L0 = None
            return
        angle = self._check_angle(angle_deg)
        lo, hi = self.angle_range_deg
        self._intended_L0 = self.fits.length_L0(math.radians(min(max(angle, lo), hi)))

    @property
    def last(self) -> ArmSample:
        """The latest output."""
        if self._last is None:
            raise RuntimeError("call ArmChain.reset before using the chain")
        return self._last

    @property
    def spindle_state(self) -> core.SpindleState:
        """A copy of the spindles' state (2 spindles: BRA, TRImed)."""
        return self._state.copy()

    # -- pushes ----------------------------------------------------------------------------
    def push_counts(self, t_s: float, counts: float) -> ArmSample:
        """One encoder reading taken at ``t_s``."""
        t = self._time(t_s)
        if t is None:
            return self._rejected()
        reading = _real(counts)
        if not is_valid_reading(reading, self.config.encoder.max_count):
            self.counters["invalid_reading"] += 1
            return self._rejected()
        return self._atomic(self._counts_stage, t, reading)

    def push_angle(self, t_s: float, angle_deg: float) -> ArmSample:
        """One clean elbow-angle sample (deg), skipping the sensor stage."""
        t = self._time(t_s)
        if t is None:
            return self._rejected()
        angle = _real(angle_deg)
        if not math.isfinite(angle):
            self.counters["invalid_angle"] += 1
            return self._rejected()
        return self._atomic(self._angle_stage, t, angle, -1.0, -1.0)

    def push_lengths(self, t_s: float, length_L0: np.ndarray,
                     angle_deg: float | None = None) -> ArmSample:
        """One sample of the two fibre lengths (L0), skipping the sensor and length model.

        ``angle_deg`` is only recorded in the output (the last known angle if None or not a
        finite real number).
        """
        t = self._time(t_s)
        if t is None:
            return self._rejected()
        L = self._check_lengths(length_L0)
        if L is None:
            self.counters["invalid_length"] += 1
            return self._rejected()
        angle = self._angle if angle_deg is None else _real(angle_deg)
        if not math.isfinite(angle):
            angle = self._angle
        return self._atomic(self._length_stage, t, L, angle, -1.0, -1.0)

    # -- blocks: many samples per call (an env step, a sensor buffer) ---------------------
    def push_counts_block(self, t_s: np.ndarray, counts: np.ndarray) -> ArmSample:
        """Push readings ``counts`` (k,) taken at ``t_s`` (k,) in order; return the last output.

        Exactly ``push_counts`` sample by sample (counters included); a backend may do it in
        one call.
        """
        for t, x in zip(*_block("counts", t_s, counts, ()), strict=True):
            self.push_counts(t, x)
        return self.last

    def push_angle_block(self, t_s: np.ndarray, angle_deg: np.ndarray) -> ArmSample:
        """``push_angle`` over (k,) times and angles; return the last output."""
        for t, x in zip(*_block("angle_deg", t_s, angle_deg, ()), strict=True):
            self.push_angle(t, x)
        return self.last

    def push_lengths_block(self, t_s: np.ndarray, length_L0: np.ndarray) -> ArmSample:
        """``push_lengths`` over (k,) times and (k, 2) lengths; return the last output."""
        for t, x in zip(*_block("length_L0", t_s, length_L0, (2,)), strict=True):
            self.push_lengths(t, x)
        return self.last

    # -- stages ----------------------------------------------------------------------------
    def _atomic(self, stage: Callable[..., ArmSample], *args) -> ArmSample:
        # A stage changes the median, the predictor, the spindles and the counters before its
        # last spindle step; if anything raises, all of it goes back (the C chain works on a
        # copy of its state for the same reason).
        median, predictor = self._median.snapshot(), self._fusimotor.predictor.snapshot()
        counters, state, behind = dict(self.counters), self._state, self._behind
        arrays = [getattr(state, name).copy() for name in _SPINDLE_ARRAYS]
        try:
            return stage(*args)
        except BaseException:
            self._median.restore(median)
            self._fusimotor.predictor.restore(predictor)
            self.counters, self._state, self._behind = counters, state, behind
            for name, saved in zip(_SPINDLE_ARRAYS, arrays, strict=True):
                getattr(state, name)[...] = saved
            raise

    def _counts_stage(self, t: float, reading: float) -> ArmSample:
        if self._restarts(t):
            return self._angle_stage(t, float(self.config.calibration.angle_deg(reading)),
                                     reading, reading)
        filtered = self._median.push(reading)
        angle = float(self.config.calibration.angle_deg(filtered))
        return self._angle_stage(t, angle, reading, filtered)

    def _angle_stage(self, t: float, angle: float, counts: float, filtered: float) -> ArmSample:
        given = angle
        if not self._restarts(t):  # a restart starts afresh at the new angle
            limit = self.config.max_speed_deg_s * (t - self._t)
            if abs(angle - self._angle) > limit:
                self.counters["slew_limited"] += 1
                angle = self._angle + math.copysign(limit, angle - self._angle)
        clamped, angle = self._clamp_angle(angle)
        if clamped:
            self.counters["angle_clamped"] += 1
        L = self.fits.length_L0(math.radians(angle))
        return self._length_stage(t, L, angle, counts, filtered, given)

    def _length_stage(self, t: float, L_in: np.ndarray, angle: float, counts: float,
                      filtered: float, given_angle: float | None = None) -> ArmSample:
        dt = t - self._t
        if dt > self.config.gap_s:
            self.counters["gaps"] += 1
        if self._restarts(t):
            self.counters["restarts"] += 1
            self.counters["clock_resyncs"] += int(t < self._t)
            self.counters["accepted"] += 1
            # the median restarts on the sample's own reading (an encoder's, or the one of
            # the angle as given, as reset does)
            reading = counts if counts >= 0 else self._rest_reading(
                angle if given_angle is None else given_angle)
            return self._rest(t, angle, L_in, reading, counts, filtered)
        limit = self.config.max_speed_L0_s * dt
        change = L_in - self._u
        if np.any(np.abs(change) > limit):
            self.counters["slew_limited"] += 1
            L_in = L_in - change + np.clip(change, -limit, limit)
        x0, v0 = self._x, self._v
        if self._omega is None:
            x1 = L_in
            v1 = (x1 - x0) / dt
            a1 = (v1 - v0) / dt
        else:
            x1, v1, a1 = tracking_step(x0, v0, self._u, L_in, dt, self._omega)
        template_in = x1 if self._intended_L0 is None else self._intended_L0
        template, gs, gd = self._fusimotor.update(t, template_in)
        ia, ii = self._advance_spindles(x0, v0, x1, v1, gd, gs, dt)
        self._u, self._x, self._v, self._a = L_in, x1, v1, a1
        self._angle, self._t = angle, t
        self._behind = 0
        self.counters["accepted"] += 1
        self._last = ArmSample(t, True, counts, filtered, angle, x1, v1, a1, template, gs, gd,
                               ia, ii)
        return self._last

    def _rest(self, t: float, angle: float, L: np.ndarray, reading: float, counts: float,
              filtered: float) -> ArmSample:
        """At rest at ``angle`` / lengths ``L`` at ``t``: what reset and a restart share."""
        template_in = L if self._intended_L0 is None else self._intended_L0
        template, gs, gd = self._fusimotor.reset(t, template_in)
        state = core.equilibrium_state(L, gd, gs, self.config.params)
        ia, ii = core.afferents(state, self.config.params)
        self._median.reset(reading)
        self._state = state
        self._u = L.copy()
        self._x = L.copy()
        self._v = np.zeros(2)
        self._a = np.zeros(2)
        self._angle = angle
        self._t = t
        self._behind = 0
        self._last = ArmSample(t, True, counts, filtered, angle, L.copy(), self._v.copy(),
                               self._a.copy(), template, gs, gd, ia, ii)
        return self._last

    def _advance_spindles(self, x0, v0, x1, v1, gd, gs, dt):
        c, theta = self._columns, self._method.theta
        k = max(1, math.ceil(dt / self.config.spindle_step_s * (1 - 1e-12)))
        h = dt / k
        lo, hi = core.LENGTH_RANGE_L0
        reach = self.config.max_speed_L0_s * h
        previous = x0
        for j in range(1, k):
            w = hermite_weights(j / k, 1)
            Ls = w[0] * x0 + w[1] * x1 + dt * (w[2] * v0 + w[3] * v1)
            # Within the spindle's range, a slew-limited step from the previous sub-step, and
            # still able to reach x1 at that speed (a bridge whose end velocities disagree
            # would otherwise overshoot both).
            left = reach * (k - j)
            Ls = np.minimum(np.maximum(Ls, previous - reach), previous + reach)
            Ls = np.minimum(np.maximum(Ls, x1 - left), x1 + left)
            Ls = np.minimum(np.maximum(Ls, lo), hi)
            core.commit(self._state, core.advance(self._state, Ls, gd, gs, h, theta, c),
                        Ls, gd, gs)
            previous = Ls
        new = core.advance(self._state, x1, gd, gs, h, theta, c)
        core.commit(self._state, new, x1, gd, gs)
        return core._afferents(new[0], x1, c)

    # -- checks ----------------------------------------------------------------------------
    def _time(self, t_s: float) -> float | None:
        """The sample's time, or None (counted) if it may not be pushed."""
        if self._last is None:
            raise RuntimeError("call ArmChain.reset before pushing samples")
        t = _real(t_s)
        if not math.isfinite(t):
            self.counters["bad_time"] += 1
            return None
        if t == self._t:
            self.counters["repeated_time"] += 1
            return None
        if t < self._t:
            self._behind += 1
            if self._behind < self.config.resync_after_samples:
                self.counters["time_backwards"] += 1
                return None
        return t

    def _restarts(self, t: float) -> bool:
        # an earlier time that _time let through is a clock resync
        return t < self._t or t - self._t > self.config.max_bridge_s

    def _clamp_angle(self, angle: float) -> tuple[bool, float]:
        lo, hi = self.angle_range_deg
        if lo <= angle <= hi:
            return False, angle
        return True, min(max(angle, lo), hi)

    def _rest_reading(self, angle: float) -> float:
        # The reading at that angle, clamped to what an encoder can read: with exact lengths
        # the angle is only recorded and may lie anywhere.
        with np.errstate(over="ignore"):
            counts = float(self.config.calibration.counts(angle))
        return min(max(counts, 0.0), float(self.config.encoder.max_count))

    def _rejected(self) -> ArmSample:
        last = self.last
        return ArmSample(**{f.name: getattr(last, f.name) for f in fields(ArmSample)
                            if f.name != "accepted"}, accepted=False)

    @staticmethod
    def _check_angle(angle_deg: float) -> float:
        angle = _real(angle_deg)
        if not math.isfinite(angle):
            raise ValueError(f"angle_deg={angle_deg!r} must be a finite real number")
        return angle

    @staticmethod
    def _check_lengths(length_L0: np.ndarray) -> np.ndarray | None:
        L = _real_array(length_L0)
        lo, hi = core.LENGTH_RANGE_L0
        if L.shape != (2,) or not np.all(np.isfinite(L)) or L.min() < lo or L.max() > hi:
            return None
        return L.copy()


_SPINDLE_ARRAYS = ("tension_FU", "polar_velocity_L0_s", "velocity_root", "activation",
                   "length_L0", "gamma_dyn_pps", "gamma_stat_pps")


def _check_positive_int(name: str, value: object, most: int | None = None) -> None:
    if (isinstance(value, bool | np.bool_) or not isinstance(value, int | np.integer)
            or value < 1 or (most is not None and value > most)):
        limit = "" if most is None else f" and <= {most}"
        raise ValueError(f"{name}={value!r} must be an integer >= 1{limit}")


def _check_positive_real(name: str, value: object) -> None:
    if isinstance(value, bool | np.bool_) or not (math.isfinite(_real(value))
                                                  and _real(value) > 0):
        raise ValueError(f"{name}={value!r} must be a finite real number > 0")


def _real(value: object) -> float:
    """``value`` as a float; NaN if it is not one real number (complex, an integer beyond
    float's range, a string, None...), so the caller's rule for non-finite input applies."""
    if isinstance(value, complex | np.complexfloating) or (
            isinstance(value, np.ndarray) and np.iscomplexobj(value)):
        return math.nan
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _real_array(value: object) -> np.ndarray:
    """``value`` as a float array; NaN in place of every element that is not a real number
    (all of them if the array is complex)."""
    if np.iscomplexobj(value):
        return np.full(np.shape(value), math.nan)
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        try:
            items = np.asarray(value, dtype=object)
        except ValueError:  # ragged
            return np.full(1, math.nan)
        return np.vectorize(_real, otypes=[float])(items) if items.size else np.zeros(
            items.shape)


@dataclass(frozen=True)
class ChainTrace:
    """Every signal of a batch run; arrays have the samples on axis 0, muscles on axis 1.

    Fields are those of :class:`ArmSample` stacked over samples, plus the final counters.
    """

    t_s: np.ndarray
    accepted: np.ndarray
    counts: np.ndarray
    counts_filtered: np.ndarray
    angle_deg: np.ndarray
    length_L0: np.ndarray
    velocity_L0_s: np.ndarray
    acceleration_L0_s2: np.ndarray
    template_L0: np.ndarray
    gamma_static_pps: np.ndarray
    gamma_dynamic_pps: np.ndarray
    ia_pps: np.ndarray
    ii_pps: np.ndarray
    counters: dict[str, int]

    def columns(self) -> dict[str, np.ndarray]:
        """Flat named columns (per-muscle signals split as ``BRA_ia_pps`` ...), e.g. for CSV."""
        out: dict[str, np.ndarray] = {}
        for f in fields(ArmSample):
            value = getattr(self, f.name)
            if value.ndim == 2:
                for k, muscle in enumerate(MUSCLES):
                    out[f"{muscle}_{f.name}"] = value[:, k]
            else:
                out[f.name] = value
        return out


def run_chain(
    t_s: np.ndarray,
    *,
    counts: np.ndarray | None = None,
    angle_deg: np.ndarray | None = None,
    length_L0: np.ndarray | None = None,
    intended_angle_deg: np.ndarray | None = None,
    config: ChainConfig | None = None,
    fits: LengthFits | None = None,
) -> ChainTrace:
    """Run the chain over a whole trace; exactly what :class:`ArmChain` does sample by sample.

    Give the samples' times ``t_s`` (T,) and one of ``counts`` (T,) encoder readings,
    ``angle_deg`` (T,) elbow angles or ``length_L0`` (T, 2) fibre lengths. The arm starts at
    rest at the first sample that is valid (its output is that rest state, its angle clamped to
    the length model's range and counted like any other sample's); the other samples
    are pushed in order (bad ones are handled by the documented rules). ``intended_angle_deg``
    (T,) switches the fusimotor template to the intended motion.
    """
    given = [x is not None for x in (counts, angle_deg, length_L0)]
    if sum(given) != 1:
        raise ValueError("give exactly one of counts, angle_deg or length_L0")
    t = _real_array(t_s)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t_s must be a non-empty 1-D array, got shape {t.shape}")
    signal = _real_array(next(x for x in (counts, angle_deg, length_L0) if x is not None))
    want = (t.size, 2) if length_L0 is not None else (t.size,)
    if signal.shape != want:
        raise ValueError(f"the signal has shape {signal.shape}, expected {want} for t_s "
                         f"{t.shape}")
    intended = None
    if intended_angle_deg is not None:
        intended = _intended_angles(intended_angle_deg)
        if intended.shape != t.shape:
            raise ValueError(f"intended_angle_deg has shape {intended.shape}, expected {t.shape}")

    chain = ArmChain(config, fits)
    start = _first_valid(t, signal, counts is not None, length_L0 is not None, chain)
    if counts is not None:
        chain.reset(float(chain.config.calibration.angle_deg(signal[start])), t[start])
        push = chain.push_counts
    elif angle_deg is not None:
        chain.reset(signal[start], t[start])
        push = chain.push_angle
    else:
        lo, hi = chain.angle_range_deg
        chain.reset(0.5 * (lo + hi), t[start], length_L0=signal[start])
        push = chain.push_lengths
    run_trace = getattr(chain, "run_trace", None)
    if run_trace is not None:  # a backend that runs the whole trace in one call
        first = chain.last
        rest = run_trace(push.__name__, t[start + 1:], signal[start + 1:],
                         None if intended is None else intended[start + 1:])
        stacked = {
            f.name: np.concatenate([np.array([getattr(first, f.name)] * (start + 1)),
                                    rest[f.name]]) for f in fields(ArmSample)
        }
    else:
        samples = [chain.last] * (start + 1)
        for i in range(start + 1, t.size):
            if intended is not None:
                chain.set_intended_angle(None if np.isnan(intended[i]) else intended[i])
            samples.append(push(t[i], signal[i]))
        stacked = {
            f.name: np.array([getattr(s, f.name) for s in samples]) for f in fields(ArmSample)
        }
    stacked["accepted"][:start] = False
    return ChainTrace(**stacked, counters=dict(chain.counters))


def _intended_angles(value: object) -> np.ndarray:
    """``run_chain``'s intended angles as floats: real numbers, NaN for the measured motion."""
    why = "must hold real angles in deg (NaN: the measured motion)"
    if np.iscomplexobj(value):
        raise ValueError(f"intended_angle_deg {why}, got complex values")
    try:
        intended = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"intended_angle_deg {why}: {exc}") from None
    if np.isinf(intended).any():
        raise ValueError(f"intended_angle_deg {why}, got an infinite one")
    return intended


def _first_valid(t, signal, is_counts, is_lengths, chain) -> int:
    for i in range(t.size):
        if not np.isfinite(t[i]):
            continue
        if is_counts:
            ok = is_valid_reading(signal[i], chain.config.encoder.max_count)
        elif is_lengths:
            ok = chain._check_lengths(signal[i]) is not None
        else:
            ok = bool(np.isfinite(signal[i]))
        if ok:
            return i
    raise ValueError("the trace holds no valid sample to start from")


def _block(name: str, t_s: np.ndarray, signal: np.ndarray,
           sample_shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    t = _real_array(t_s)
    x = _real_array(signal)
    if t.ndim != 1 or x.shape != (t.size, *sample_shape):
        raise ValueError(f"{name} has shape {x.shape} and t_s {t.shape}; expected "
                         f"{(t.size, *sample_shape)} for (k,) times")
    return t, x
