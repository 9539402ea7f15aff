"""Fault injection for the arm chain: a seeded stream of servo samples with random faults,
pushed through the numpy and the C backend side by side, and the checks of the soak.

``scripts/fault_soak.py`` is the command line; :func:`run_soak` is the whole run.

The stream (:func:`fault_stream`) is what an encoder on a moving servo delivers: minimum-jerk
moves between random elbow angles at 40-450 deg/s peak (the servo's no-load speed is 684
deg/s) separated by holds, read at ~500 Hz with jitter, noise and the encoder's own rare
invalid readings (:class:`proprio_env.body.encoder.Encoder`). Mostly encoder counts
(``push_counts``), with runs of clean angles (``push_angle``) and fitted lengths
(``push_lengths``). Between runs it injects one fault (:data:`FAULTS`):

- dropouts from one sample to five minutes (log-uniform), half of them during a movement
  (above 40 deg/s), half at rest, and
  rare clock jumps of 10^3 to 10^7 s; a burst of invalid readings (a dead encoder);
- corrupted times: repeated, backwards, NaN, +-inf, 1e9, 1e9 s ahead, 1e308, the Python int
  10**400, 1e-9 s after the last one;
- corrupted values: NaN, +-inf, spikes inside the valid range, out-of-range and non-integer
  readings, the Python int 10**400; for angles and lengths the same classes;
- the servo's load word (the force sense: every counts sample carries one, the simulated
  AX-12 load reading of a smooth servo torque with its own rare invalid words,
  :class:`proprio_env.body.encoder.LoadSensor`): a run of invalid words (the dropout code -1,
  NaN, +-inf, words above 2047, fractions, negatives, 10**400, complex numbers) on samples
  whose angle is good (``load_invalid``), or a run pushed with no load at all
  (``load_missing``).

A fault is pushed on its own (single push) or inside a block of clean samples
(``push_*_block``), each half the time; clean runs go in blocks of 1-64 samples, a quarter of
them sample by sample. Both backends get exactly the same calls.

Checks (:class:`SoakReport`): every counter delta equal between the backends after every
call; every returned output finite, with Ia, II and Ib in [0, :data:`RATE_BOUND_PPS`],
tendon forces >= 0 and lengths in :data:`spindle.core.LENGTH_RANGE_L0`; the max |numpy - C|
of Ia and II below :data:`RATE_DIFF_LIMIT_PPS` and of Ib below :data:`IB_DIFF_LIMIT_PPS`; no
push raises; no single call runs longer than ``max_call_s``; never stuck: after each fault,
of the clean samples that follow (valid time and value, which every rule accepts) until the
next fault or :data:`RECOVERY_WINDOW` of them, at most ``resync_after_samples - 1`` are
rejected (the clock-resync rule's cost after a corrupt time far ahead; every other fault
costs none); resident memory flat (growth from 10 % to 100 % of the run below
:data:`RSS_GROWTH_LIMIT_MB`).

A backend that raises is left as it is for the next calls (so a chain that stays broken
shows as ``stuck``); after :data:`STUCK_AFTER` failing calls in a row, or a call stopped by
the time limit (its state is then undefined; that call is left out of the counter
comparison), both chains are reset at the next clean sample and the run goes on
(``resyncs``).
"""

from __future__ import annotations

import math
import os
import resource
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from proprio_env.body.encoder import Encoder, LoadSensor
from spindle import core
from spindle.chain import BACKENDS, COUNTERS, ArmChain, ArmSample, ChainConfig, make_chain
from spindle.chain.length_model import LengthFits
from spindle.chain.sensor import AX12, Calibration, is_valid_reading

RATE_BOUND_PPS = 1000.0
"""Physiological bound of the Ia and II rates (pps): human spindle afferents fire below
~200-300 pps; 1000 pps is above any rate the model gives in its valid range (the issue's
failures were 10^3-10^6 pps)."""
RATE_DIFF_LIMIT_PPS = 1e-6
"""Largest accepted |numpy - C| of a rate (pps); the backends agree to ~1e-12 pps."""
IB_DIFF_LIMIT_PPS = 1e-9
"""Largest accepted |numpy - C| of an Ib rate (pps; issue 24's target)."""
RSS_GROWTH_LIMIT_MB = 20.0
"""Largest accepted growth of resident memory between 10 % and 100 % of the run (MB)."""
RECOVERY_WINDOW = 50
"""Clean samples after a fault over which recovery is measured (fewer if the next fault comes
first)."""
STUCK_AFTER = 3
"""Failing calls in a row after which a backend counts as stuck and both are reset."""
DROPOUT_RANGE_S = (AX12.period_s, 300.0)
CLOCK_JUMP_RANGE_S = (1e3, 1e7)
ANGLE_RANGE_DEG = (5.0, 125.0)

FAULTS = (
    "dropout_moving", "dropout_rest", "clock_jump", "dead_encoder",
    "time_repeat", "time_backwards", "time_nan", "time_inf", "time_neg_inf", "time_1e9",
    "time_jump_1e9", "time_1e308", "time_pyint", "time_tiny_step",
    "value_nan", "value_inf", "value_neg_inf", "value_spike", "value_out_of_range",
    "value_non_integer", "value_pyint", "load_invalid", "load_missing",
)
"""Names of the injected faults (``dropout_*`` is labelled by the motion at its start)."""
_FAULT_WEIGHTS = {"dropout": 0.3, "clock_jump": 0.02, "dead_encoder": 0.04, "time": 0.27,
                  "value": 0.27, "load": 0.1}
_TIME_FAULTS = tuple(f for f in FAULTS if f.startswith("time_"))
_VALUE_FAULTS = tuple(f for f in FAULTS if f.startswith("value_"))
_LOAD_FAULTS = tuple(f for f in FAULTS if f.startswith("load_"))
_BAD_LOAD_WORDS = (-1, math.nan, math.inf, -math.inf, 2048, 4095, 65535, 3.5, -3, 10**400,
                   complex(5.0, 1.0))
ENTRIES = ("counts", "angle", "lengths")


@dataclass(frozen=True)
class Segment:
    """One call on each chain: ``push_<entry>`` per sample (``single``) or one block call.

    Attributes:
        entry: ``"counts"``, ``"angle"`` or ``"lengths"``.
        t_s, values: what is pushed (Python objects: faults may be NaN, ints beyond float).
        clean: per sample, True if every rule must accept it (valid, later time and value).
        true_t_s, true_angle_deg: the real clock and elbow angle of each sample.
        single: push sample by sample instead of one block call.
        fault: the injected fault's name ("" for a clean run).
        loads: the load word beside each sample (counts only; None: pushed without load).
    """

    entry: str
    t_s: list
    values: list
    clean: list[bool]
    true_t_s: list[float]
    true_angle_deg: list[float]
    single: bool
    fault: str = ""
    loads: list | None = None


class ServoMotion:
    """A servo's elbow angle: minimum-jerk moves between random angles, and holds."""

    def __init__(self, rng: np.random.Generator, t0_s: float = 0.0,
                 angle_deg: float = 65.0) -> None:
        self.rng = rng
        self._piece = (t0_s, t0_s, angle_deg, angle_deg)

    def _next_piece(self, t_s: float) -> None:
        if self.rng.random() < 0.45:  # hold
            a1 = self._piece[3]
            self._piece = (t_s, t_s + float(self.rng.uniform(0.02, 1.5)), a1, a1)
        else:
            self.start_move(t_s)

    def start_move(self, t_s: float) -> None:
        """A move starting at ``t_s`` (> the current piece's start) from where the arm is,
        to a random angle at least 20 deg away, at 80-450 deg/s peak."""
        a0 = self.angle_deg(t_s)
        lo, hi = ANGLE_RANGE_DEG
        target = float(self.rng.uniform(lo, hi - 20.0))
        target = target + 20.0 if target > a0 - 20.0 else target
        peak_deg_s = float(self.rng.uniform(80.0, 450.0))
        duration = 1.875 * abs(target - a0) / peak_deg_s  # min-jerk: peak = 1.875 mean
        self._piece = (t_s, t_s + duration, a0, target)

    def angle_deg(self, t_s: float) -> float:
        if t_s > self._piece[1] + 10.0:  # long unobserved: the arm may be anywhere now
            a = float(self.rng.uniform(*ANGLE_RANGE_DEG))
            self._piece = (t_s, t_s, a, a)
        while t_s > self._piece[1]:
            self._next_piece(self._piece[1])
        t0, t1, a0, a1 = self._piece
        if t1 == t0:
            return a1
        s = (t_s - t0) / (t1 - t0)
        return a0 + (a1 - a0) * s**3 * (10 - 15 * s + 6 * s * s)

    def speed_deg_s(self, t_s: float) -> float:
        self.angle_deg(t_s)
        t0, t1, a0, a1 = self._piece
        if t1 == t0 or a0 == a1:
            return 0.0
        s = (t_s - t0) / (t1 - t0)
        return abs(a1 - a0) / (t1 - t0) * 30 * s * s * (1 - s) ** 2


def fault_stream(rng: np.random.Generator, n_samples: int, fits: LengthFits,
                 fault_probability: float = 0.2) -> Iterator[Segment]:
    """Segments of a servo's sample stream with faults, about ``n_samples`` samples in all.

    ``fits`` turns angles into the lengths of ``push_lengths`` runs. Deterministic for a
    seeded ``rng``.
    """
    stream = _StreamWriter(rng, fits)
    entry, run_left, done = "counts", 0, 0
    while done < n_samples:
        if run_left <= 0:
            entry = str(rng.choice(ENTRIES, p=[0.8, 0.1, 0.1]))
            run_left = int(rng.integers(100, 1500))
        fault = _draw_fault(rng, fault_probability)
        if fault in _LOAD_FAULTS and entry != "counts":
            fault = ""  # only encoder samples carry a load word
        stream.start_segment()
        if not fault:
            stream.add_clean(entry, int(rng.integers(1, 65)))
            single = bool(rng.random() < 0.25)
        else:
            single, fault = stream.add_fault(entry, fault)
        ts, values = stream.ts, stream.values
        if any(isinstance(x, int) and abs(x) > 2**53 for x in ts + _flat(values)):
            single = True  # a Python int beyond float cannot go into a float block
        if any(isinstance(v, complex) for v in _flat(values) + stream.loads):
            single = True
        if any(isinstance(x, int) and abs(x) > 2**53 for x in stream.loads):
            single = True
        if entry == "lengths" and any(len(v) != 2 for v in values):
            single = True
        done += len(ts)
        run_left -= len(ts)
        loads = stream.loads if entry == "counts" and fault != "load_missing" else None
        yield Segment(entry, ts, values, stream.clean, stream.true_t, stream.true_a, single,
                      fault, loads)


def _draw_fault(rng: np.random.Generator, fault_probability: float) -> str:
    """The fault of the next segment ("" for none)."""
    if not rng.random() < fault_probability:
        return ""
    fault = str(rng.choice(list(_FAULT_WEIGHTS), p=list(_FAULT_WEIGHTS.values())))
    if fault == "time":
        return str(rng.choice(_TIME_FAULTS))
    if fault == "value":
        return str(rng.choice(_VALUE_FAULTS))
    if fault == "load":
        return str(rng.choice(_LOAD_FAULTS))
    return fault


class _StreamWriter:
    """The servo, its encoder and clock, and the segment being written by :func:`fault_stream`:
    times pushed, values, whether each is clean, the true time and angle."""

    def __init__(self, rng: np.random.Generator, fits: LengthFits):
        self.rng = rng
        self.fits = fits
        self.encoder = Encoder(AX12, Calibration(), rng=rng)
        self.load_sensor = LoadSensor(rng=rng)
        self.motion = ServoMotion(rng)
        self.clock = 0.0   # the true time of the last sample delivered
        self.last_t = 0.0  # the last time pushed (a corrupted one included)
        self.start_segment()

    def start_segment(self) -> None:
        self.ts, self.values, self.clean, self.true_t, self.true_a = [], [], [], [], []
        self.loads: list = []

    def add(self, t: object, value: object, ok: bool, t_true: float, a_true: float) -> None:
        for column, item in zip((self.ts, self.values, self.clean, self.true_t, self.true_a),
                                (t, value, ok, t_true, a_true), strict=True):
            column.append(item)
        torque = np.array([servo_torque_Nm(t_true)])
        self.loads.append(float(self.load_sensor.read_block(torque)[0]))
        if ok:
            self.last_t = t_true

    def sample(self) -> tuple[float, float]:
        """The next sample's true time and angle."""
        self.clock = self.encoder.next_sample_time_s(self.clock)
        return self.clock, self.motion.angle_deg(self.clock)

    def add_clean(self, entry: str, n: int) -> None:
        """``n`` samples as the servo delivers them."""
        for _ in range(n):
            t, a = self.sample()
            v = self.value_of(entry, a)
            self.add(t, v, entry != "counts" or is_valid_reading(v, AX12.max_count), t, a)

    def lengths(self, angle: float) -> list[float]:
        return [float(v) for v in self.fits.length_L0(math.radians(angle))]

    def value_of(self, kind: str, angle: float) -> object:
        if kind == "counts":
            return self.encoder.read(angle)
        return angle if kind == "angle" else self.lengths(angle)

    def add_fault(self, entry: str, fault: str) -> tuple[bool, str]:
        """The fault, with a few clean samples around it when it goes in a block; returns
        (whether the segment is pushed sample by sample, the fault's name)."""
        rng = self.rng
        single = bool(rng.random() < 0.5)
        self.add_clean(entry, 0 if single else int(rng.integers(0, 8)))
        if fault in ("dropout", "clock_jump"):
            fault = self.add_gap(entry, fault)
        elif fault == "dead_encoder":
            for _ in range(int(rng.integers(2, 200))):
                t, a = self.sample()
                dead = {"counts": -1, "angle": math.nan}.get(entry, [math.nan] * 2)
                self.add(t, dead, False, t, a)
        elif fault == "load_invalid":
            for _ in range(int(rng.integers(1, 30))):
                self.add_clean(entry, 1)
                self.loads[-1] = _BAD_LOAD_WORDS[int(rng.integers(len(_BAD_LOAD_WORDS)))]
        elif fault == "load_missing":
            self.add_clean(entry, int(rng.integers(1, 30)))
        elif fault.startswith("time_"):
            t, a = self.sample()
            bad_t = self.corrupt_time(fault, t)
            if fault == "time_tiny_step":
                self.clock = bad_t  # the true clock: a sample 1 ns after the last
            self.add(bad_t, self.value_of(entry, a), False, t, a)
        else:
            t, a = self.sample()
            self.add(t, self.corrupt_value(entry, fault, a), False, t, a)
        self.add_clean(entry, 0 if single else int(rng.integers(0, 8)))
        return single, fault

    def add_gap(self, entry: str, fault: str) -> str:
        """A dropout or a clock jump, then one sample; returns the fault's name (a dropout
        is "dropout_moving" or "dropout_rest")."""
        lo, hi = DROPOUT_RANGE_S if fault == "dropout" else CLOCK_JUMP_RANGE_S
        motion = self.motion
        if fault == "dropout":
            # Half during a movement (above 40 deg/s), half at rest: clean samples until the
            # motion is so (a hold lasts at most 1.5 s).
            moving = bool(self.rng.random() < 0.5)
            if moving and motion.speed_deg_s(self.clock) <= 40.0:
                motion.start_move(self.clock)
            for _ in range(2000):
                if (motion.speed_deg_s(self.clock) > 40.0) == moving:
                    break
                self.add_clean(entry, 1)
            fault = ("dropout_moving" if motion.speed_deg_s(self.clock) > 40.0
                     else "dropout_rest")
        self.clock += math.exp(self.rng.uniform(math.log(lo), math.log(hi)))
        self.add_clean(entry, 1)
        return fault

    def corrupt_value(self, kind: str, fault: str, angle: float) -> object:
        rng = self.rng
        if fault == "value_nan":
            return math.nan if kind != "lengths" else [math.nan, 1.0]
        if fault == "value_inf":
            return math.inf if kind != "lengths" else [1.0, math.inf]
        if fault == "value_neg_inf":
            return -math.inf if kind != "lengths" else [-math.inf, -math.inf]
        if fault == "value_pyint":
            return 10**400 if kind != "lengths" else [10**400, 1.0]
        if fault == "value_spike":  # valid, far from the motion
            if kind == "counts":
                return int(rng.integers(0, AX12.max_count + 1))
            if kind == "angle":
                return angle + float(rng.choice([-1, 1]) * rng.uniform(60.0, 200.0))
            return [float(v) for v in rng.uniform(*core.LENGTH_RANGE_L0, 2)]
        if fault == "value_out_of_range":
            if kind == "counts":
                return int(rng.choice([-1, -5, AX12.max_count + 1, 4095, 65535]))
            if kind == "angle":
                return float(rng.choice([-40.0, -0.5, 131.0, 400.0, 1e12]))
            return [float(rng.choice([0.2, 0.49, 1.51, 3.0])), 1.0]
        if fault == "value_non_integer":
            if kind == "counts":
                return float(self.encoder.read(angle)) + float(rng.choice([0.5, 0.25, -0.1]))
            if kind == "angle" or rng.random() < 0.5:  # a complex number
                return (complex(angle, 1.0) if kind == "angle"
                        else [complex(*self.lengths(angle)), 1.0])
            return self.lengths(angle)[:1]  # the wrong shape
        raise AssertionError(fault)

    def corrupt_time(self, fault: str, t: float) -> object:
        rng, last_t = self.rng, self.last_t
        return {"time_repeat": last_t, "time_backwards": last_t - float(rng.uniform(1e-4, 10)),
                "time_nan": math.nan, "time_inf": math.inf, "time_neg_inf": -math.inf,
                "time_1e9": 1e9, "time_jump_1e9": t + 1e9, "time_1e308": 1e308,
                "time_pyint": 10**400, "time_tiny_step": last_t + 1e-9}[fault]


def servo_torque_Nm(t_s: float) -> float:
    """The servo's joint torque the load words read (N m): a smooth load within the AX-12's
    1.5 N m, flexion and extension."""
    return 0.8 * math.sin(2 * math.pi * 0.5 * t_s) + 0.3 * math.sin(2 * math.pi * 2.3 * t_s)


def _flat(values: list) -> list:
    return [x for v in values for x in (v if isinstance(v, list) else [v])]


class CallTimeout(Exception):
    """A push call ran longer than the soak's limit (unbounded work)."""


class _Watchdog:
    """Raises :class:`CallTimeout` in a Python-level call that exceeds ``limit_s`` (main
    thread only; a C call is interrupted only when it returns)."""

    def __init__(self, limit_s: float | None) -> None:
        self.active = (limit_s is not None and hasattr(signal, "setitimer")
                       and threading.current_thread() is threading.main_thread())
        self.limit_s = limit_s

    def __enter__(self) -> _Watchdog:
        if self.active:
            self._old = signal.signal(signal.SIGALRM, self._fire)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.active:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, self._old)

    def _fire(self, signum: int, frame: object) -> None:
        raise CallTimeout(f"a push call ran longer than {self.limit_s} s")

    def arm(self) -> None:
        if self.active:
            signal.setitimer(signal.ITIMER_REAL, self.limit_s)

    def disarm(self) -> None:
        if self.active:
            signal.setitimer(signal.ITIMER_REAL, 0)


def rss_mb() -> float:
    """Resident memory of this process now (MB); the peak where /proc is missing."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@dataclass
class SoakReport:
    """What the soak measured; :attr:`failures` lists the checks that failed."""

    samples: int = 0
    calls: int = 0
    faults: Counter = field(default_factory=Counter)
    counters: dict[str, Counter] = field(
        default_factory=lambda: {b: Counter() for b in BACKENDS})
    counter_mismatches: int = 0
    first_mismatch: str = ""
    max_rate_diff_pps: float = 0.0
    max_ib_diff_pps: float = 0.0
    compared_outputs: int = 0
    nonfinite: Counter = field(default_factory=Counter)
    out_of_bounds: Counter = field(default_factory=Counter)
    max_rate_pps: dict[str, float] = field(default_factory=lambda: dict.fromkeys(BACKENDS, 0.0))
    max_ib_pps: dict[str, float] = field(default_factory=lambda: dict.fromkeys(BACKENDS, 0.0))
    errors: Counter = field(default_factory=Counter)
    error_examples: dict[tuple, str] = field(default_factory=dict)
    stuck: Counter = field(default_factory=Counter)
    resyncs: int = 0
    timeouts: Counter = field(default_factory=Counter)
    recovery: dict[str, list[int]] = field(default_factory=dict)
    """Per fault, the clean samples rejected after each occurrence."""
    allowed_rejections: int = 0
    """Most clean samples a fault may cost (``resync_after_samples - 1``)."""
    wall_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(BACKENDS, 0.0))
    max_call_s: dict[str, float] = field(default_factory=lambda: dict.fromkeys(BACKENDS, 0.0))
    rss_10_MB: float = math.nan
    rss_end_MB: float = math.nan
    peak_rss_MB: float = math.nan

    @property
    def counters_equal(self) -> bool:
        return self.counter_mismatches == 0 and (self.counters["numpy"]
                                                  == self.counters["c"])

    @property
    def rss_growth_MB(self) -> float:
        return self.rss_end_MB - self.rss_10_MB

    @property
    def not_recovered(self) -> Counter:
        return Counter({f: sum(x > self.allowed_rejections for x in v)
                        for f, v in self.recovery.items()
                        if any(x > self.allowed_rejections for x in v)})

    @property
    def failures(self) -> list[str]:
        out = []
        if not self.counters_equal:
            out.append(f"counters differ between backends after {self.counter_mismatches} "
                       f"calls (first: {self.first_mismatch})")
        if sum(self.nonfinite.values()):
            out.append(f"non-finite outputs: {dict(self.nonfinite)}")
        if sum(self.out_of_bounds.values()):
            out.append(f"outputs out of bounds (Ia/II/Ib in [0, {RATE_BOUND_PPS:g}] pps, "
                       f"forces >= 0, lengths in {core.LENGTH_RANGE_L0} L0): "
                       f"{dict(self.out_of_bounds)}")
        if not self.max_rate_diff_pps <= RATE_DIFF_LIMIT_PPS:
            out.append(f"max |numpy - C| rate {self.max_rate_diff_pps:.3g} pps > "
                       f"{RATE_DIFF_LIMIT_PPS:g}")
        if not self.max_ib_diff_pps <= IB_DIFF_LIMIT_PPS:
            out.append(f"max |numpy - C| Ib {self.max_ib_diff_pps:.3g} pps > "
                       f"{IB_DIFF_LIMIT_PPS:g}")
        if sum(self.errors.values()):
            out.append(f"pushes raised: {dict(self.errors)}")
        if sum(self.timeouts.values()):
            out.append(f"calls stopped after the time limit: {dict(self.timeouts)}")
        if sum(self.stuck.values()):
            out.append(f"stuck (failing {STUCK_AFTER} calls in a row): {dict(self.stuck)}")
        if self.not_recovered:
            out.append(f"not recovered after faults (more than {self.allowed_rejections} of "
                       f"the next {RECOVERY_WINDOW} clean samples rejected): "
                       f"{dict(self.not_recovered)}")
        if not self.rss_growth_MB < RSS_GROWTH_LIMIT_MB:
            out.append(f"RSS grew {self.rss_growth_MB:.1f} MB from 10 % to 100 % of the run "
                       f"(limit {RSS_GROWTH_LIMIT_MB:g} MB)")
        return out

    @property
    def ok(self) -> bool:
        return not self.failures

    def table(self) -> str:
        """The summary table (plain text)."""
        rows = [("check", "numpy", "c")]
        rows += [(f"counter {name}", str(self.counters["numpy"][name]),
                  str(self.counters["c"][name])) for name in COUNTERS]
        for label, per in (("wall time (s)", {b: f"{self.wall_s[b]:.2f}" for b in BACKENDS}),
                           ("longest call (s)",
                            {b: f"{self.max_call_s[b]:.3f}" for b in BACKENDS}),
                           ("max Ia/II (pps)", {b: f"{self.max_rate_pps[b]:.1f}"
                                                for b in BACKENDS}),
                           ("max Ib (pps)", {b: f"{self.max_ib_pps[b]:.1f}" for b in BACKENDS}),
                           ("non-finite outputs", self.nonfinite),
                           ("out-of-bounds outputs", self.out_of_bounds),
                           ("pushes raised", {b: sum(n for (bb, *_), n in self.errors.items()
                                                     if bb == b) for b in BACKENDS}),
                           ("calls timed out", self.timeouts), ("stuck", self.stuck)):
            rows.append((label, str(per.get("numpy", 0)), str(per.get("c", 0))))
        width = [max(len(r[i]) for r in rows) for i in range(3)]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, width, strict=True)) for r in rows]
        lines.insert(1, "  ".join("-" * w for w in width))
        lines += ["", f"samples {self.samples}, calls {self.calls}, outputs compared "
                      f"{self.compared_outputs}, max |numpy - C| {self.max_rate_diff_pps:.3g} "
                      f"pps (Ib {self.max_ib_diff_pps:.3g} pps), resyncs {self.resyncs}",
                  f"RSS at 10 % {self.rss_10_MB:.1f} MB, at 100 % {self.rss_end_MB:.1f} MB, "
                  f"peak {self.peak_rss_MB:.1f} MB",
                  "faults (count, most clean samples rejected after one): " + ", ".join(
                      f"{f} {self.faults[f]} ({max(self.recovery.get(f, [0]))})"
                      for f in FAULTS if self.faults[f])]
        for key, message in self.error_examples.items():
            lines.append(f"raised: {key[0]} on {key[1]}: {key[2]}: {message}")
        lines += ["FAIL: " + f for f in self.failures] or ["all checks passed"]
        return "\n".join(lines)

    def last_line(self) -> str:
        return (f"fault_soak samples={self.samples} counters_equal={self.counters_equal} "
                f"max_rate_diff_pps={self.max_rate_diff_pps:.3g} "
                f"max_ib_diff_pps={self.max_ib_diff_pps:.3g} "
                f"rss_growth_MB={self.rss_growth_MB:.1f} "
                f"nonfinite={sum(self.nonfinite.values())} "
                f"out_of_bounds={sum(self.out_of_bounds.values())} "
                f"raised={sum(self.errors.values())} stuck={sum(self.stuck.values())} "
                f"ok={self.ok}")


def _push(chain: ArmChain, seg: Segment) -> list[ArmSample]:
    """The outputs a call returns: each sample's for single pushes, the last for a block."""
    push = getattr(chain, f"push_{seg.entry}")
    if seg.loads is not None:  # counts with their load words
        if seg.single:
            return [push(t, v, w) for t, v, w in zip(seg.t_s, seg.values, seg.loads,
                                                     strict=True)]
        return [chain.push_counts_block(np.array(seg.t_s, dtype=float),
                                        np.array(seg.values, dtype=float),
                                        load=np.array(seg.loads, dtype=float))]
    if seg.single:
        return [push(t, v) for t, v in zip(seg.t_s, seg.values, strict=True)]
    block = getattr(chain, f"push_{seg.entry}_block")
    return [block(np.array(seg.t_s, dtype=float), np.array(seg.values, dtype=float))]


def _check_output(s: ArmSample, backend: str, report: SoakReport) -> None:
    values = np.concatenate([np.atleast_1d(np.asarray(getattr(s, f), dtype=float))
                             for f in ("t_s", "counts", "counts_filtered", "angle_deg",
                                       "length_L0", "velocity_L0_s", "acceleration_L0_s2",
                                       "template_L0", "gamma_static_pps", "gamma_dynamic_pps",
                                       "ia_pps", "ii_pps", "torque_Nm", "force_N", "ib_pps")])
    if not np.all(np.isfinite(values)):
        report.nonfinite[backend] += 1
        return
    rates = np.concatenate([s.ia_pps, s.ii_pps, s.ib_pps])
    lo, hi = core.LENGTH_RANGE_L0
    report.max_rate_pps[backend] = max(report.max_rate_pps[backend],
                                       float(max(s.ia_pps.max(), s.ii_pps.max())))
    report.max_ib_pps[backend] = max(report.max_ib_pps[backend], float(s.ib_pps.max()))
    if (rates.min() < 0 or rates.max() > RATE_BOUND_PPS or s.length_L0.min() < lo
            or s.length_L0.max() > hi or s.force_N.min() < 0):
        report.out_of_bounds[backend] += 1


def run_soak(n_samples: int, seed: int = 0, config: ChainConfig | None = None,
             max_call_s: float | None = 5.0, fault_probability: float = 0.2,
             progress: Callable[[int], None] | None = None,
             chains: dict[str, ArmChain] | None = None) -> SoakReport:
    """Push about ``n_samples`` samples with faults through both backends; the report.

    ``config`` (its ``backend`` is ignored) is the chains' setting; ``max_call_s`` stops a
    call that runs longer (``None``: no limit); ``fault_probability``: of a fault before each
    run of clean samples (1-64 samples); ``progress(k)`` is called with the number of samples
    of each call. ``chains`` replaces the two chains (keys ``"numpy"``, ``"c"``), e.g. to
    check the checks.
    """
    config = ChainConfig() if config is None else config
    if chains is None:
        chains = {b: make_chain(replace(config, backend=b)) for b in BACKENDS}
    fits = chains["numpy"].fits
    rng = np.random.default_rng(seed)
    report = SoakReport(allowed_rejections=config.resync_after_samples - 1)
    for c in chains.values():
        c.reset(65.0, 0.0)
    failing = dict.fromkeys(BACKENDS, 0)
    need_resync = False
    watching: list[list] = []  # [fault, clean seen, clean accepted] per open window
    ten_percent = max(1, n_samples // 10)
    with _Watchdog(max_call_s) as dog:
        for seg in fault_stream(rng, n_samples, fits, fault_probability):
            if need_resync:
                k = next((i for i, ok in enumerate(seg.clean) if ok), 0)
                for c in chains.values():
                    c.reset(seg.true_angle_deg[k], seg.true_t_s[k] - 1e-3)
                report.resyncs += 1
                failing = dict.fromkeys(BACKENDS, 0)
            report.calls += 1
            if seg.fault:
                report.faults[seg.fault] += 1
            outputs, deltas, need_resync = _push_to_both(chains, seg, dog, report, failing)
            _compare_backends(report, seg, outputs, deltas)
            watching = _track_recovery(report, watching, seg, deltas)
            before_n = report.samples
            report.samples += len(seg.t_s)
            if before_n < ten_percent <= report.samples:
                report.rss_10_MB = rss_mb()
            if progress is not None:
                progress(len(seg.t_s))
    for w in watching:
        report.recovery.setdefault(w[0], []).append(w[2])
    report.rss_end_MB = rss_mb()
    report.peak_rss_MB = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    if math.isnan(report.rss_10_MB):
        report.rss_10_MB = report.rss_end_MB
    return report


def _push_to_both(chains, seg: Segment, dog: _Watchdog, report: SoakReport,
                  failing: dict[str, int]):
    """Push ``seg`` into each chain, timed and watched; returns (outputs by backend, counter
    changes by backend, whether the chains must be resynchronised)."""
    outputs, deltas, timed_out, need_resync = {}, {}, False, False
    for b, c in chains.items():
        before = dict(c.counters)
        t0 = time.perf_counter()
        try:
            dog.arm()
            try:
                outputs[b] = _push(c, seg)
            finally:
                dog.disarm()
        except CallTimeout:
            report.timeouts[b] += 1
            timed_out = need_resync = True
        except Exception as exc:  # a push must not raise: record and go on
            key = (b, seg.fault or "clean", type(exc).__name__)
            report.errors[key] += 1
            report.error_examples.setdefault(key, str(exc)[:160])
            failing[b] += 1
            if failing[b] >= STUCK_AFTER:
                report.stuck[b] += 1
                need_resync = True
        else:
            failing[b] = 0
        elapsed = time.perf_counter() - t0
        report.wall_s[b] += elapsed
        report.max_call_s[b] = max(report.max_call_s[b], elapsed)
        after = c.counters
        deltas[b] = Counter({k: after[k] - before.get(k, 0) for k in after})
    if timed_out:  # the stopped chain's state is undefined: not compared
        deltas = {b: Counter() for b in BACKENDS}
    return outputs, deltas, need_resync


def _compare_backends(report: SoakReport, seg: Segment, outputs, deltas) -> None:
    """Count the counters' changes, check each output and compare the two backends'."""
    for b in BACKENDS:
        report.counters[b].update(deltas[b])
    if deltas["numpy"] != deltas["c"]:
        report.counter_mismatches += 1
        if not report.first_mismatch:
            diff = {k: (deltas["numpy"][k], deltas["c"][k])
                    for k in set(deltas["numpy"]) | set(deltas["c"])
                    if deltas["numpy"][k] != deltas["c"][k]}
            report.first_mismatch = (f"call {report.calls} ({seg.fault or 'clean'}, "
                                     f"{seg.entry}): numpy, c = {diff}")
    for b, outs in outputs.items():
        for s in outs:
            _check_output(s, b, report)
    if len(outputs) == 2:
        for sn, sc in zip(outputs["numpy"], outputs["c"], strict=True):
            diff = max(float(np.max(np.abs(sn.ia_pps - sc.ia_pps))),
                       float(np.max(np.abs(sn.ii_pps - sc.ii_pps))))
            report.max_rate_diff_pps = max(report.max_rate_diff_pps,
                                           diff if math.isfinite(diff) else math.inf)
            ib = float(np.max(np.abs(sn.ib_pps - sc.ib_pps)))
            report.max_ib_diff_pps = max(report.max_ib_diff_pps,
                                         ib if math.isfinite(ib) else math.inf)
            report.compared_outputs += 1


def _track_recovery(report: SoakReport, watching: list[list], seg: Segment,
                    deltas) -> list[list]:
    """Recovery: clean samples rejected after a fault (on either chain), until the next
    fault, which would otherwise be blamed on this one; returns the open windows."""
    if seg.fault:
        for w in watching:
            report.recovery.setdefault(w[0], []).append(w[2])
        return [[seg.fault, 0, 0]]
    n_clean = sum(seg.clean)
    accepted = min(deltas[b].get("accepted", 0) for b in BACKENDS)
    for w in watching:
        w[1] += n_clean
        w[2] += max(0, n_clean - accepted)
    for w in [w for w in watching if w[1] >= RECOVERY_WINDOW]:
        report.recovery.setdefault(w[0], []).append(w[2])
        watching.remove(w)
    return watching
