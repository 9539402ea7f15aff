"""The seed paper's processing chain for one arm: encoder counts in, Ia and II out.

    counts -> median filter (7) -> f(x) -> elbow angle -> fitted BRA/TRImed fibre lengths
           -> tracking low-pass (L, dL/dt) -> PI template -> gamma_s = h, gamma_d = g
           -> Mileusnic spindles (HUMAN gains) -> Ia, II per muscle
    load word -> joint torque -> BRA/TRImed tendon forces (moment arms at the angle)
           -> Golgi tendon organs (Lin & Crago 2002, HUMAN) -> Ib per muscle

The force sense (``docs/gto.md``): each accepted sample's load word becomes a joint torque
(:func:`~spindle.chain.sensor.load_torque_Nm`), split into BRA and TRImed tendon forces at the
conditioned angle (:func:`~spindle.chain.force.tendon_forces_N`: flexion torque to BRA,
extension to TRImed, never negative), and the tendon organs are stepped exactly over the
sample's interval in ONE step (the force a line between the two samples; the step is exact
for a log stage linear over the step, :mod:`spindle.tendon_organ`), not on the spindles'
sub-steps. Restarts and resets put them at rest at the sample's force.

This is what would run on the prosthesis, so it needs no MuJoCo. :class:`ArmChain` streams:
push samples as they come and read the rates. It is the one-arm view (``n_arms = 1``) of
:class:`spindle.chain.batch.ArmChainBatch`, where every stage and every rule below is
written once over a leading axis of arms; this class only turns scalars into one-arm arrays
and back. :func:`spindle.chain.run_chain` takes a whole trace and returns every intermediate
signal; it is the chain driven sample by sample (:meth:`ArmChain.run_trace`), so the two agree
exactly. The C chain, :class:`spindle.native.chain.CArmChain`, follows the same rules.

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
  the angle given to :meth:`ArmChain.reset` (so :func:`run_chain`'s first sample) included;
- ``invalid_load``: an accepted sample whose load word is not an integer in 0..2047 (the
  dropout code -1, a corrupted word, NaN, anything not a real number): the torque of the
  last accepted sample is held (0 after a reset), the sample itself is accepted (its angle
  is good). At a reset the word's torque is 0 (nothing to hold), counted too;
- ``missing_load``: an accepted encoder sample pushed without a load word (``load=None``):
  zero torque, so the tendon organs relax towards rest at zero force (a chain never given a
  load keeps Ib at 0). Angle and length pushes carry no load: zero torque, not counted.
  A rejected sample changes nothing, its load word included.

Values that are not one real number (:mod:`spindle.number_rule`: complex numbers, integers too
large for a float, strings, bytes, bools, ``None``) count as non-finite: a bad sample above, or
``ValueError`` from
:meth:`ArmChain.reset`. The spindles' sub-step lengths (the Hermite curve across each
interval) are kept within the spindle's range (0.5-1.5 L0), within ``max_speed_L0_s`` of the
previous sub-step and able to reach the new length at that speed, so a bridge never leaves
the valid range however the motion before it went. A push is atomic: if it raises (a spindle
step that fails), the chain, its counters included, is left exactly as it was.
"""

from __future__ import annotations

import math

import numpy as np

from spindle import core, number_rule
from spindle.chain.batch import ArmChainBatch
from spindle.chain.config import COUNTERS, ArmSample, ChainConfig, real_number
from spindle.chain.length_model import LengthFits
from spindle.chain.samples import (
    block_inputs,
    check_loads,
    checked_angle,
    checked_lengths,
    stack_samples,
)
from spindle.tendon_organ import TendonOrganState


class ArmChain:
    """The streaming chain of one arm (BRA and TRImed), in numpy: the one-arm view of
    :class:`~spindle.chain.batch.ArmChainBatch`.

    Call :meth:`reset` once, then push samples in increasing time. Each accepted push
    advances the spindles from the previous sample's time to the new one. The C chain
    (:class:`spindle.native.chain.CArmChain`) has the same API; :func:`spindle.chain.make_chain`
    builds the one ``config.backend`` names.

    Args:
        config: :class:`~spindle.chain.config.ChainConfig` (``backend`` ``"numpy"`` or
            ``"auto"``, which here means numpy: ``make_chain`` resolves it; ``"c"`` raises).
        fits: the length fits (default: ``config.fits_path``'s).
    """

    backend = "numpy"

    def __init__(self, config: ChainConfig | None = None, fits: LengthFits | None = None):
        if config is not None and config.backend == "c":
            raise ValueError(
                "ArmChain is the numpy chain, but config.backend='c'; build the chain with "
                "spindle.chain.make_chain(config, fits)")
        self._arms = ArmChainBatch(1, config, fits)
        self.config = self._arms.config
        self.fits = self._arms.fits
        self.angle_range_deg = self._arms.angle_range_deg
        self.length_min_L0, self.length_max_L0 = self._arms.length_min_L0, self._arms.length_max_L0
        self._ready = False

    # -- state ---------------------------------------------------------------------------
    def reset(self, angle_deg: float, t_s: float = 0.0,
              length_L0: np.ndarray | None = None, load: float | None = None) -> ArmSample:
        """The arm at rest at ``angle_deg`` (and, if given, exact ``length_L0``) at ``t_s``.

        Filters start on that angle, the template on those lengths, the spindles at
        equilibrium with the resulting drive, the tendon organs at rest at the force of the
        load word ``load`` (None: no load, zero torque; an invalid word: zero torque, counted
        ``invalid_load``). Counters restart at zero; without
        ``length_L0``, an angle outside the length model's range is clamped to it and counted
        (``angle_clamped``), as a pushed angle is. The switch returns to the measured motion.
        """
        t = real_number(t_s)
        if not math.isfinite(t):
            raise ValueError(f"t_s={t_s!r} must be a finite real number")
        angle = checked_angle(angle_deg)
        lengths = None
        if length_L0 is not None:
            lengths = checked_lengths(length_L0)
            if lengths is None:
                raise ValueError(f"length_L0={length_L0!r} must be 2 finite lengths within "
                                 f"{core.LENGTH_RANGE_L0} L0")
            lengths = lengths[None]
        self._arms.reset(np.array([angle]), t, lengths,
                         load=None if load is None else [real_number(load)])
        self._ready = True
        return self.last

    def set_intended_angle(self, angle_deg: float | None) -> None:
        """The switch: drive the fusimotor template from an intended elbow angle (deg).

        ``None`` returns to the measured motion. The intended angle holds until changed (an
        angle outside the length model's range is clamped to it); call it before each push to
        follow an intended trajectory.
        """
        self._arms.set_intended_angle(None if angle_deg is None
                                      else np.array([checked_angle(angle_deg)]))

    @property
    def last(self) -> ArmSample:
        """The latest output."""
        self._check_ready()
        return self._arms.last.arm(0)

    @property
    def counters(self) -> dict[str, int]:
        """Each counter of :data:`~spindle.chain.config.COUNTERS` since the last reset."""
        return {name: int(value[0]) for name, value in self._arms.counters.items()}

    @property
    def spindle_state(self) -> core.SpindleState:
        """A copy of the spindles' state (2 spindles: BRA, TRImed)."""
        return self._arms.spindle_state

    @property
    def tendon_organ_state(self) -> TendonOrganState:
        """A copy of the tendon organs' state (2 organs: BRA, TRImed)."""
        return self._arms.tendon_organ_state

    # -- pushes ----------------------------------------------------------------------------
    def push_counts(self, t_s: float, counts: float, load: float | None = None) -> ArmSample:
        """One encoder reading taken at ``t_s``, with the servo's load word ``load`` read
        beside it (None: no load reading; the load rules of the module)."""
        self._check_ready()
        return self._arms.push_counts([real_number(t_s)], [real_number(counts)],
                                      load=None if load is None else [real_number(load)]
                                      ).arm(0)

    def push_angle(self, t_s: float, angle_deg: float) -> ArmSample:
        """One clean elbow-angle sample (deg), skipping the sensor stage."""
        self._check_ready()
        return self._arms.push_angle([real_number(t_s)], [real_number(angle_deg)]).arm(0)

    def push_lengths(self, t_s: float, length_L0: np.ndarray,
                     angle_deg: float | None = None) -> ArmSample:
        """One sample of the two fibre lengths (L0), skipping the sensor and length model.

        ``angle_deg`` is only recorded in the output (the last known angle if None or not a
        finite real number).
        """
        self._check_ready()
        lengths = checked_lengths(length_L0)
        lengths = np.full((1, 2), math.nan) if lengths is None else lengths[None]
        angle = math.nan if angle_deg is None else real_number(angle_deg)
        return self._arms.push_lengths([real_number(t_s)], lengths, angle_deg=[angle]).arm(0)

    # -- blocks: many samples per call (an env step, a sensor buffer) ---------------------
    def push_counts_block(self, t_s: np.ndarray, counts: np.ndarray,
                          load: np.ndarray | None = None) -> ArmSample:
        """Push readings ``counts`` (k,) taken at ``t_s`` (k,) in order, with load words
        ``load`` (k,) (None: no load readings); return the last output.

        Exactly ``push_counts`` sample by sample (counters included), in one block pass.
        """
        return self._block("counts", self._arms.push_counts_block, t_s, counts, (), load)

    def push_angle_block(self, t_s: np.ndarray, angle_deg: np.ndarray) -> ArmSample:
        """``push_angle`` over (k,) times and angles; return the last output."""
        return self._block("angle_deg", self._arms.push_angle_block, t_s, angle_deg, ())

    def push_lengths_block(self, t_s: np.ndarray, length_L0: np.ndarray) -> ArmSample:
        """``push_lengths`` over (k,) times and (k, 2) lengths; return the last output."""
        return self._block("length_L0", self._arms.push_lengths_block, t_s, length_L0, (2,))

    def run_trace(self, push: str, t_s: np.ndarray, signal: np.ndarray,
                  intended_angle_deg: np.ndarray | None = None,
                  load: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Push a whole trace; every output stacked (what :func:`spindle.chain.run_chain` uses).

        ``push`` names the entry point (``"push_counts"``, ``"push_angle"``,
        ``"push_lengths"``); ``intended_angle_deg`` (k,) sets the switch before each sample
        (NaN: the measured motion); ``load`` (k,) the load words beside counts (only with
        ``"push_counts"``). Returns the fields of :class:`ArmSample` stacked over the k
        samples (rejected ones included). Here a plain loop; the C chain makes one call.
        """
        kind = push.removeprefix("push_")
        t, x = block_inputs(kind, t_s, signal, (2,) if kind == "lengths" else ())
        words = check_loads(push, load, t.shape)
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
            samples.append(push_one(t[i], x[i]) if words is None
                           else push_one(t[i], x[i], words[i]))
        return stack_samples(samples, self.last)

    # -- helpers ---------------------------------------------------------------------------
    def _block(self, name, push_block, t_s, signal, sample_shape, load=None) -> ArmSample:
        self._check_ready()
        t, x = block_inputs(name, t_s, signal, sample_shape)
        if load is None:
            push_block(t[None], x[None])
        else:
            push_block(t[None], x[None], load=check_loads("push_counts", load, t.shape)[None])
        return self.last

    def _check_ready(self) -> None:
        if not self._ready:
            raise RuntimeError("call ArmChain.reset before using the chain")


__all__ = ["COUNTERS", "ArmChain"]
