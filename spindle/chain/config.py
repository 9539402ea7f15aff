"""Settings and outputs of the prosthesis chain, shared by its numpy and C implementations.

:data:`MUSCLES` (the project's one muscle order), :data:`COUNTERS` (the handling rules'
names), :data:`BACKENDS`, :class:`ChainConfig` (every setting), :class:`ArmSample` (one
output), and the coercion of pushed values to real numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from spindle import core
from spindle.backends import BACKEND_CHOICES, DEFAULT_BACKEND
from spindle.backends import BACKENDS as BACKENDS  # re-exported: the one table lives there
from spindle.chain.conditioning import natural_rad_s
from spindle.chain.fusimotor import SEED_PAPER, FusimotorParams
from spindle.chain.sensor import AX12, AX12_LOAD, Calibration, EncoderParams, LoadParams
from spindle.methods import get_method
from spindle.number_rule import check_fields, positive_int

# the chain's bad-sample rule, under the names its pushes use
from spindle.number_rule import sample_array as real_array  # noqa: F401
from spindle.number_rule import sample_number as real_number  # noqa: F401
from spindle.params import HUMAN, SpindleParams
from spindle.tendon_organ_params import (
    ARM26_MAX_ISOMETRIC_FORCE_N,
    TendonOrganParams,
    force_scales_N,
)
from spindle.tendon_organ_params import HUMAN as GTO_HUMAN
from spindle.tendon_organ_params import MAX_STEP_S as GTO_MAX_STEP_S

MUSCLES = ("BRA", "TRImed")
"""The muscles of the arm, in the order of every per-muscle axis of the project."""
MAX_SLEW_LIMIT_L0_S = core.MAX_SPEED_L0_S * (1.0 - 1e-9)
"""The largest ``max_speed_L0_s``: the spindle's speed limit less a rounding margin, so that no
sub-step the slew limit allows can round above the limit the C spindle step checks (at exactly
10 L0/s the C chain refused such sub-steps, ``PS_ERR_SPEED``, where numpy took them)."""

COUNTERS = (
    "accepted", "invalid_reading", "invalid_angle", "invalid_length", "repeated_time",
    "time_backwards", "bad_time", "gaps", "slew_limited", "angle_clamped", "restarts",
    "clock_resyncs", "invalid_load", "missing_load",
)
"""Names of :attr:`ArmChain.counters` (:mod:`spindle.chain.arm` describes each rule)."""
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
        fusimotor: :class:`~spindle.chain.fusimotor.FusimotorParams`.
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
        max_speed_L0_s: slew limit of the lengths (L0/s), at most :data:`MAX_SLEW_LIMIT_L0_S`
            (below the spindle's 10 L0/s by a rounding margin).
        fits_path: length fits (``None``: the bundled ``models/length_fits.json``).
        load: the servo's load reading (:class:`~spindle.chain.sensor.LoadParams`, default
            :data:`~spindle.chain.sensor.AX12_LOAD`): the torque a load word stands for.
        gto: the tendon organs' constants (default the human preset,
            :data:`spindle.tendon_organ_params.HUMAN`).
        max_isometric_force_N: BRA's and TRImed's maximum isometric forces (N, default
            Arm26's), from which each muscle's force scale G2 follows
            (:func:`~spindle.tendon_organ_params.force_scales_N`).
        moment_arm_fits_path: the moment-arm tables (``None``: the bundled
            ``models/moment_arm_fits.json``) that turn joint torque into tendon forces.
        backend: ``"numpy"``, ``"c"`` or ``"auto"`` (:data:`BACKEND_CHOICES`);
            :func:`spindle.chain.make_chain` (and :func:`~spindle.chain.make_batched_chain`)
            builds the chain it names. ``"auto"`` is ``"c"`` when the C library can be used
            (a valid cached build, or a working C compiler that builds it on first use) and
            ``"numpy"`` otherwise, never an error (:func:`spindle.chain.resolve_backend`); the
            chain built records the resolved name in its ``config.backend``.
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
    max_speed_L0_s: float = core.SLEW_LIMIT_L0_S
    fits_path: str | Path | None = None
    load: LoadParams = AX12_LOAD
    gto: TendonOrganParams = GTO_HUMAN
    max_isometric_force_N: tuple[float, float] = (ARM26_MAX_ISOMETRIC_FORCE_N["BRA"],
                                                  ARM26_MAX_ISOMETRIC_FORCE_N["TRImed"])
    moment_arm_fits_path: str | Path | None = None
    backend: str = DEFAULT_BACKEND

    def __post_init__(self) -> None:
        # the project's number rule (spindle.number_rule): a bool, a string or a complex value
        # is a mistake here, and a numpy scalar is kept as the Python number it stands for
        object.__setattr__(self, "median_window",
                           positive_int("median_window", self.median_window))
        object.__setattr__(self, "resync_after_samples", positive_int(
            "resync_after_samples", self.resync_after_samples, high=MAX_RESYNC_AFTER_SAMPLES))
        if self.median_window % 2 == 0:
            raise ValueError(f"median_window={self.median_window!r} must be an odd integer >= 1")
        optional = tuple(name for name in ("lowpass_hz", "step_s", "max_gap_s")
                         if getattr(self, name) is not None)
        check_fields(self, (*optional, "max_bridge_s", "max_speed_deg_s", "max_speed_L0_s"),
                     low=0.0, low_open=True)
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
        if not float(self.max_speed_L0_s) <= MAX_SLEW_LIMIT_L0_S:
            raise ValueError(
                f"max_speed_L0_s={self.max_speed_L0_s!r} must lie in (0, "
                f"{MAX_SLEW_LIMIT_L0_S!r}] L0/s: below the spindle's {core.MAX_SPEED_L0_S} L0/s "
                "speed limit by a rounding margin (a sub-step at exactly the limit can round "
                "above it)"
            )
        if not float(self.max_bridge_s) <= GTO_MAX_STEP_S:
            raise ValueError(
                f"max_bridge_s={self.max_bridge_s!r} must be <= {GTO_MAX_STEP_S} s: the tendon "
                "organs step each bridged interval in one exact step, at most that long")
        forces = tuple(float(f) for f in self.max_isometric_force_N)
        if len(forces) != len(MUSCLES):
            raise ValueError(f"max_isometric_force_N={self.max_isometric_force_N!r} needs one "
                             f"force per muscle of {MUSCLES}")
        force_scales_N(self.gto, forces)  # G2 >= MIN_FORCE_SCALE_N, or ValueError naming them
        object.__setattr__(self, "max_isometric_force_N", forces)
        if not isinstance(self.backend, str) or self.backend not in BACKEND_CHOICES:
            raise ValueError(f"backend={self.backend!r} is not one of {BACKEND_CHOICES}")

    @property
    def gap_s(self) -> float:
        if self.max_gap_s is not None:
            return float(self.max_gap_s)
        return self.median_window * self.encoder.period_s

    @property
    def force_scale_N(self) -> np.ndarray:
        """G2 (N) of BRA and TRImed: the preset's, scaled by each maximum isometric force."""
        return force_scales_N(self.gto, self.max_isometric_force_N)

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
        torque_Nm: the joint torque the load reading stands for (N m, flexion positive; the
            last valid one held over an invalid word, 0 without a load reading).
        length_L0: conditioned (low-passed) fibre length.
        velocity_L0_s, acceleration_L0_s2: its first and second time derivatives.
        template_L0: the fusimotor template (PI predictor output).
        gamma_static_pps, gamma_dynamic_pps: fusimotor drive.
        ia_pps, ii_pps: primary and secondary afferent rates.
        force_N: the tendon forces carrying ``torque_Nm`` at ``angle_deg`` (N, >= 0;
            :func:`spindle.chain.force.tendon_forces_N`).
        ib_pps: the Golgi tendon organs' Ib rates (pps, >= 0).
    """

    t_s: float
    accepted: bool
    counts: float
    counts_filtered: float
    angle_deg: float
    torque_Nm: float
    length_L0: np.ndarray
    velocity_L0_s: np.ndarray
    acceleration_L0_s2: np.ndarray
    template_L0: np.ndarray
    gamma_static_pps: np.ndarray
    gamma_dynamic_pps: np.ndarray
    ia_pps: np.ndarray
    ii_pps: np.ndarray
    force_N: np.ndarray
    ib_pps: np.ndarray


SCALAR_OUTPUTS = ("t_s", "counts", "counts_filtered", "angle_deg", "torque_Nm")
"""The outputs of :class:`ArmSample` that are one number per arm (the rest: one per muscle)."""


class Chain(Protocol):
    """What both chains (numpy :class:`~spindle.chain.arm.ArmChain`, C
    :class:`~spindle.native.chain.CArmChain`) offer and :func:`spindle.chain.run_chain` uses.

    Both also have the per-sample pushes (``push_counts`` with its ``load``, ``push_angle``,
    ``push_lengths``), their ``*_block`` forms, ``set_intended_angle`` and ``spindle_state``.
    """

    config: ChainConfig
    angle_range_deg: tuple[float, float]

    @property
    def counters(self) -> dict[str, int]: ...

    @property
    def last(self) -> ArmSample: ...

    def reset(self, angle_deg: float, t_s: float = 0.0,
              length_L0: np.ndarray | None = None, load: float | None = None
              ) -> ArmSample: ...

    def run_trace(self, push: str, t_s: np.ndarray, signal: np.ndarray,
                  intended_angle_deg: np.ndarray | None = None,
                  load: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Push a whole trace through entry point ``push`` (``"push_counts"``...), setting
        the switch from ``intended_angle_deg`` before each sample, with the load words
        ``load`` beside counts; the stacked outputs."""
        ...
