"""The seed paper's processing chain for one arm: encoder counts in, Ia and II out.

    counts -> median filter (7) -> f(x) -> elbow angle -> fitted BRA/TRImed fibre lengths
           -> tracking low-pass (L, dL/dt) -> PI template -> gamma_s = h, gamma_d = g
           -> Mileusnic spindles (HUMAN gains) -> Ia, II per muscle

This is what would run on the prosthesis, so it needs no MuJoCo. :class:`ArmChain` (numpy)
streams: push samples as they come and read the rates. :func:`spindle.chain.run_chain` takes
a whole trace and returns every intermediate signal; it is the chain driven sample by sample
(:meth:`ArmChain.run_trace`), so the two agree exactly. The C chain,
:class:`spindle.native.chain.CArmChain`, follows the same rules.

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
from dataclasses import fields

import numpy as np

from spindle import core, number_rule
from spindle.chain.conditioning import natural_rad_s, tracking_step
from spindle.chain.config import (
    COUNTERS,
    MUSCLES,
    ArmSample,
    ChainConfig,
    real_array,
    real_number,
)
from spindle.chain.fusimotor import Fusimotor
from spindle.chain.length_model import LengthFits, load_length_fits
from spindle.chain.sensor import MedianFilter, is_valid_reading
from spindle.methods import get_method
from spindle.substeps import bounded_hermite_length, substeps

LENGTH_RANGE_POINTS = 1301
"""Points of the angle grid over the fitted range on which each muscle's length range (the
fusimotor's h(x) and g(x) span) is taken; ``FIT_RANGE_POINTS`` in ``chain.c`` is the same."""


def fits_and_ranges(config: ChainConfig, fits: LengthFits | None
                    ) -> tuple[LengthFits, tuple[float, float], np.ndarray, np.ndarray]:
    """The chain's length fits (``fits``, or those of ``config.fits_path``), the angle range
    they hold (deg) and each muscle's shortest and longest length over it (L0): what both
    the single and the batched chain clamp to and span h(x) with."""
    fits = fits if fits is not None else load_length_fits(config.fits_path)
    if fits.muscles != MUSCLES:
        raise ValueError(f"length fits are for {fits.muscles}, the chain needs {MUSCLES}")
    lo_rad, hi_rad = fits.valid_range_rad
    span = fits.length_L0(np.linspace(lo_rad, hi_rad, LENGTH_RANGE_POINTS))
    return fits, (math.degrees(lo_rad), math.degrees(hi_rad)), span.min(axis=0), span.max(axis=0)


class ArmChain:
    """The streaming chain of one arm (BRA and TRImed), in numpy.

    Call :meth:`reset` once, then push samples in increasing time. Each accepted push
    advances the spindles from the previous sample's time to the new one. The C chain
    (:class:`spindle.native.chain.CArmChain`) has the same API; :func:`spindle.chain.make_chain`
    builds the one ``config.backend`` names.
    """

    def __init__(self, config: ChainConfig | None = None, fits: LengthFits | None = None):
        self.config = ChainConfig() if config is None else config
        if self.config.backend != "numpy":
            raise ValueError(
                f"ArmChain is the numpy chain, but config.backend={self.config.backend!r}; "
                "build the chain with spindle.chain.make_chain(config, fits)")
        (self.fits, self.angle_range_deg, self.length_min_L0,
         self.length_max_L0) = fits_and_ranges(self.config, fits)
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
        t = real_number(t_s)
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
        reading = real_number(counts)
        if not is_valid_reading(reading, self.config.encoder.max_count):
            self.counters["invalid_reading"] += 1
            return self._rejected()
        return self._atomic(self._counts_stage, t, reading)

    def push_angle(self, t_s: float, angle_deg: float) -> ArmSample:
        """One clean elbow-angle sample (deg), skipping the sensor stage."""
        t = self._time(t_s)
        if t is None:
            return self._rejected()
        angle = real_number(angle_deg)
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
        angle = self._angle if angle_deg is None else real_number(angle_deg)
        if not math.isfinite(angle):
            angle = self._angle
        return self._atomic(self._length_stage, t, L, angle, -1.0, -1.0)

    # -- blocks: many samples per call (an env step, a sensor buffer) ---------------------
    def push_counts_block(self, t_s: np.ndarray, counts: np.ndarray) -> ArmSample:
        """Push readings ``counts`` (k,) taken at ``t_s`` (k,) in order; return the last output.

        Exactly ``push_counts`` sample by sample (counters included); a backend may do it in
        one call.
        """
        for t, x in zip(*block_inputs("counts", t_s, counts, ()), strict=True):
            self.push_counts(t, x)
        return self.last

    def push_angle_block(self, t_s: np.ndarray, angle_deg: np.ndarray) -> ArmSample:
        """``push_angle`` over (k,) times and angles; return the last output."""
        for t, x in zip(*block_inputs("angle_deg", t_s, angle_deg, ()), strict=True):
            self.push_angle(t, x)
        return self.last

    def push_lengths_block(self, t_s: np.ndarray, length_L0: np.ndarray) -> ArmSample:
        """``push_lengths`` over (k,) times and (k, 2) lengths; return the last output."""
        for t, x in zip(*block_inputs("length_L0", t_s, length_L0, (2,)), strict=True):
            self.push_lengths(t, x)
        return self.last

    def run_trace(self, push: str, t_s: np.ndarray, signal: np.ndarray,
                  intended_angle_deg: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Push a whole trace; every output stacked (what :func:`spindle.chain.run_chain` uses).

        ``push`` names the entry point (``"push_counts"``, ``"push_angle"``,
        ``"push_lengths"``); ``intended_angle_deg`` (k,) sets the switch before each sample
        (NaN: the measured motion). Returns the fields of :class:`ArmSample` stacked over the
        k samples (rejected ones included). Here a plain loop; the C chain makes one call.
        """
        kind = push.removeprefix("push_")
        t, x = block_inputs(kind, t_s, signal, (2,) if kind == "lengths" else ())
        if intended_angle_deg is not None:  # a setting, not a sample: the rule raises
            intended_angle_deg = number_rule.real_array("intended_angle_deg", intended_angle_deg)
        if intended_angle_deg is not None and np.shape(intended_angle_deg) != t.shape:
            raise ValueError(f"intended_angle_deg has shape {np.shape(intended_angle_deg)}, "
                             f"expected {t.shape}")
        push_one = getattr(self, push)
        samples = []
        for i in range(t.size):
            if intended_angle_deg is not None:
                angle = intended_angle_deg[i]
                self.set_intended_angle(None if np.isnan(angle) else angle)
            samples.append(push_one(t[i], x[i]))
        return stack_samples(samples, self.last)

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
        k = substeps(dt, self.config.spindle_step_s)
        h = dt / k
        reach = self.config.max_speed_L0_s * h
        previous = x0
        for j in range(1, k):
            Ls = bounded_hermite_length(j / k, x0, x1, v0, v1, dt, previous, reach,
                                        reach * (k - j))
            core.commit(self._state, core.advance(self._state, Ls, gd, gs, h, theta, c),
                        Ls, gd, gs)
            previous = Ls
        new = core.advance(self._state, x1, gd, gs, h, theta, c)
        core.commit(self._state, new, x1, gd, gs)
        return core.afferents_from_tension(new[0], x1, c)

    # -- checks ----------------------------------------------------------------------------
    def _time(self, t_s: float) -> float | None:
        """The sample's time, or None (counted) if it may not be pushed."""
        if self._last is None:
            raise RuntimeError("call ArmChain.reset before pushing samples")
        t = real_number(t_s)
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
        angle = real_number(angle_deg)
        if not math.isfinite(angle):
            raise ValueError(f"angle_deg={angle_deg!r} must be a finite real number")
        return angle

    @staticmethod
    def _check_lengths(length_L0: np.ndarray) -> np.ndarray | None:
        return checked_lengths(length_L0)


def checked_lengths(length_L0: np.ndarray) -> np.ndarray | None:
    """A copy of ``length_L0`` if it is 2 finite lengths within the spindle's range, else None."""
    L = real_array(length_L0)
    lo, hi = core.LENGTH_RANGE_L0
    if L.shape != (2,) or not np.all(np.isfinite(L)) or L.min() < lo or L.max() > hi:
        return None
    return L.copy()


_SPINDLE_ARRAYS = ("tension_FU", "polar_velocity_L0_s", "velocity_root", "activation",
                   "length_L0", "gamma_dyn_pps", "gamma_stat_pps")


def block_inputs(name: str, t_s: np.ndarray, signal: np.ndarray,
                 sample_shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(times, signal) of a block push as real arrays (NaN for anything else), shapes checked."""
    t = real_array(t_s)
    x = real_array(signal)
    if t.ndim != 1 or x.shape != (t.size, *sample_shape):
        raise ValueError(f"{name} has shape {x.shape} and t_s {t.shape}; expected "
                         f"{(t.size, *sample_shape)} for (k,) times")
    return t, x


def stack_samples(samples: list[ArmSample], like: ArmSample) -> dict[str, np.ndarray]:
    """The fields of ``samples`` stacked on axis 0 (shaped as ``like``'s when there are none)."""
    return {f.name: np.array([getattr(sample, f.name) for sample in samples]) if samples
            else np.empty((0, *np.shape(getattr(like, f.name))),
                          dtype=np.asarray(getattr(like, f.name)).dtype)
            for f in fields(ArmSample)}
