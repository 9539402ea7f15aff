"""The prosthesis' angle sensor on the device: readings, their median filter and f(x).

The seed paper reads the elbow angle from the servo (a Dynamixel AX-12 class actuator):
integer counts, 0-1023 over 300 degrees (about 0.29 deg per count), updated at about 500 Hz,
noisy. The first processing step is a median filter of window 7; a linear map f(x) then turns
counts into the joint angle.

This module holds the device-side pieces, each usable alone:

- :class:`EncoderParams` (:data:`AX12`): the device's range and rate (what the chain checks
  readings and gaps against), with the noise figures the simulated encoder
  (:class:`proprio_env.body.encoder.Encoder`) draws from;
- :func:`is_valid_reading`: integers in 0..max_count;
- :class:`Calibration`: f(x), elbow angle = sign * (counts - zero_count) * deg_per_count;
- :func:`median_filter` (a whole trace) and :class:`MedianFilter` (streaming, many
  independent signals at once: one per arm), causal;
  :func:`valid_readings` is :func:`is_valid_reading` over an array (the one rule).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from spindle.number_rule import NumberError, check_fields, positive_int

INVALID_READING = -1
"""The driver's error code for a dropped reading (what the simulated encoder returns too)."""


@dataclass(frozen=True)
class EncoderParams:
    """A servo position encoder (defaults: Dynamixel AX-12 class, as in the seed paper).

    Attributes:
        max_count: largest valid reading; valid readings are the integers 0..max_count.
        full_scale_deg: the angle spanned by 0..max_count (deg).
        sample_rate_hz: nominal reading rate (Hz).
        jitter_s: standard deviation of the sample-time jitter (s); each interval is the
            nominal period plus Gaussian jitter, clipped to +-40 % of the period so samples
            never reorder.
        noise_counts: standard deviation of Gaussian noise added before rounding (counts).
        invalid_rate: probability that a reading is invalid. Half of the invalid readings are
            dropouts (:data:`INVALID_READING`), half are corrupted 16-bit words (uniform in
            0..65535, so most fall outside 0..max_count and the rest are spikes).
    """

    max_count: int = 1023
    full_scale_deg: float = 300.0
    sample_rate_hz: float = 500.0
    jitter_s: float = 1e-4
    noise_counts: float = 0.6
    invalid_rate: float = 1e-3

    def __post_init__(self) -> None:
        object.__setattr__(self, "max_count", positive_int("max_count", self.max_count))
        check_fields(self, ("full_scale_deg", "sample_rate_hz"), low=0.0, low_open=True)
        check_fields(self, ("jitter_s", "noise_counts"), low=0.0)
        check_fields(self, ("invalid_rate",), low=0.0, high=1.0)

    @property
    def deg_per_count(self) -> float:
        """Resolution (deg per count): 300/1023 = 0.293 for the AX-12."""
        return self.full_scale_deg / self.max_count

    @property
    def period_s(self) -> float:
        """Nominal sample interval (s)."""
        return 1.0 / self.sample_rate_hz

    def ideal(self) -> EncoderParams:
        """The same device without noise, jitter or invalid readings (quantisation only)."""
        return replace(self, jitter_s=0.0, noise_counts=0.0, invalid_rate=0.0)


AX12 = EncoderParams()
"""The seed paper's servo encoder: 0-1023 over 300 deg, ~500 Hz, noisy, rare glitches."""


@dataclass(frozen=True)
class Calibration:
    """f(x): the linear map from encoder counts to elbow flexion angle.

    ``angle_deg = sign * (counts - zero_count) * deg_per_count``. The default mounts the
    servo so that its mid-range count 512 sits at the middle of the elbow's 0-130 deg range
    (65 deg) and counts grow with flexion: 0 deg reads about 290 and 130 deg about 733.

    Attributes:
        zero_count: the (fractional) reading at 0 deg elbow flexion.
        sign: +1 if counts grow with flexion, -1 if the servo is mounted the other way.
        deg_per_count: encoder resolution (deg per count).
    """

    zero_count: float = 512.0 - 65.0 / AX12.deg_per_count
    sign: int = 1
    deg_per_count: float = AX12.deg_per_count

    def __post_init__(self) -> None:
        if isinstance(self.sign, bool | np.bool_) or self.sign not in (1, -1):
            raise NumberError(f"sign={self.sign!r} must be +1 or -1")
        object.__setattr__(self, "sign", int(self.sign))
        check_fields(self, ("deg_per_count",), low=0.0, low_open=True)
        check_fields(self, ("zero_count",))

    def angle_deg(self, counts: np.ndarray | float) -> np.ndarray:
        """Elbow angle (deg) of encoder reading(s) ``counts``."""
        return self.sign * (np.asarray(counts, dtype=float) - self.zero_count) * self.deg_per_count

    def counts(self, angle_deg: np.ndarray | float) -> np.ndarray:
        """The (fractional, unquantised) reading at elbow angle(s) ``angle_deg``."""
        return self.zero_count + self.sign * np.asarray(angle_deg, dtype=float) / self.deg_per_count


def is_valid_reading(counts: float, max_count: int = AX12.max_count) -> bool:
    """True for an integer reading in 0..max_count (NaN, fractions and others are invalid):
    :func:`valid_readings` of one value."""
    try:
        x = np.float64(counts)
    except (TypeError, ValueError, OverflowError):
        return False
    return bool(valid_readings(x, max_count))


def valid_readings(counts: np.ndarray, max_count: int = AX12.max_count) -> np.ndarray:
    """Whether each reading of a float array is an integer in 0..max_count (NaN for
    non-real values fails)."""
    # comparisons with NaN are False (and raise no warning)
    with np.errstate(invalid="ignore"):
        return np.isfinite(counts) & (counts == np.floor(counts)) & (counts >= 0) & (
            counts <= max_count)


def median_filter(x: np.ndarray, window: int = 7) -> np.ndarray:
    """Causal running median along axis 0: ``out[k] = median(x[k-window+1 .. k])``.

    Before ``window`` samples exist the window is padded with the first sample (as if the
    signal had rested there), which is how :class:`MedianFilter` starts too.
    """
    _check_window(window)
    x = np.asarray(x, dtype=float)
    if x.shape[0] == 0:
        return x.copy()
    padded = np.concatenate([np.repeat(x[:1], window - 1, axis=0), x], axis=0)
    windows = np.lib.stride_tricks.sliding_window_view(padded, window, axis=0)
    return np.median(windows, axis=-1)


class MedianFilter:
    """Streaming causal medians of ``n`` independent signals, each over its own last
    ``window`` accepted samples (window odd; one signal is ``n = 1``).

    Each signal's window is a row of an (n, window) array, oldest first; :meth:`reset` fills
    it with one value (a signal at rest), as :func:`median_filter` pads its start.
    :meth:`filter` computes the medians of a block of k samples per signal (k = 1: one
    sample each) without changing the windows; :meth:`push` is that, kept.
    """

    def __init__(self, window: int = 7, n: int = 1) -> None:
        _check_window(window)
        self.window = window
        self._buffer = np.zeros((n, window))

    def reset(self, values: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Fill the windows of ``rows`` (None: all) with ``values`` (r,); return them."""
        values = np.asarray(values, dtype=float)
        self._buffer[slice(None) if rows is None else rows] = values[:, None]
        return values.copy()

    def filter(self, values: np.ndarray, n_values: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """The medians after each of ``values[i, :n_values[i]]`` (n, k) pushed in order
        (None: all k), without changing the windows: returns the medians (n, k) (entries past
        ``n_values[i]`` are padding and their medians meaningless) and the windows after the
        last, which :meth:`restore` makes the filter's."""
        n, w = self._buffer.shape
        n_values = np.full(n, values.shape[1]) if n_values is None else n_values
        extended = np.concatenate((self._buffer, values), axis=1)
        windows = np.lib.stride_tricks.sliding_window_view(extended, w, axis=1)[:, 1:]
        middle = self.window // 2
        medians = np.partition(windows, middle, axis=2)[:, :, middle]
        return medians, extended[np.arange(n)[:, None], n_values[:, None] + np.arange(w)]

    def push(self, values: np.ndarray) -> np.ndarray:
        """Push ``values`` (n, k) in order; return the medians after each (n, k)."""
        medians, self._buffer = self.filter(np.asarray(values, dtype=float))
        return medians

    def snapshot(self) -> np.ndarray:
        """The windows, for :meth:`restore` (a caller undoing a failed update)."""
        return self._buffer.copy()

    def restore(self, snapshot: np.ndarray) -> None:
        """Put back the windows a :meth:`snapshot` (or :meth:`filter`) returned (once)."""
        self._buffer = snapshot


def _check_window(window: int) -> None:
    if not (isinstance(window, int | np.integer) and window >= 1 and window % 2 == 1):
        raise ValueError(f"median window={window!r} must be an odd integer >= 1")


# -- the servo's load reading (appended: the force sense, issue 24) ---------------------------
# The AX-12 reports its present load (control table address 40-41) as an 11-bit word: bits 0-9
# the magnitude, 0..1023 as a fraction of the maximum torque, bit 10 the direction (0: CCW,
# 1: CW). It is an estimate from the motor current, not a torque sensor.

LOAD_MAGNITUDE_MAX = 1023
"""Largest load magnitude (bits 0-9): 1023 = the maximum torque."""
LOAD_DIRECTION_BIT = 1 << 10
"""Bit 10 of the load word: set for a clockwise load."""
LOAD_MAX_WORD = LOAD_DIRECTION_BIT | LOAD_MAGNITUDE_MAX
"""Largest valid load word (2047): a CW load at the maximum torque."""


@dataclass(frozen=True)
class LoadParams:
    """The servo's load reading (defaults: AX-12A).

    Attributes:
        max_torque_Nm: the torque a magnitude of 1023 stands for (N m): the AX-12A's stall
            torque at 12 V, 1.5 N m (ROBOTIS AX-12A specification), with the torque limit
            register at 1023.
        noise_counts: standard deviation of the Gaussian noise on the magnitude before
            rounding (counts; the current-based estimate is coarse).
        invalid_rate: probability that a reading is invalid (half dropouts,
            :data:`INVALID_READING`, half corrupted 16-bit words), as for the angle.
    """

    max_torque_Nm: float = 1.5
    noise_counts: float = 3.0
    invalid_rate: float = 1e-3

    def __post_init__(self) -> None:
        if not (np.isfinite(self.max_torque_Nm) and self.max_torque_Nm > 0):
            raise ValueError(f"max_torque_Nm={self.max_torque_Nm!r} must be finite and > 0")
        if not (np.isfinite(self.noise_counts) and self.noise_counts >= 0):
            raise ValueError(f"noise_counts={self.noise_counts!r} must be finite and >= 0")
        if not 0.0 <= self.invalid_rate <= 1.0:
            raise ValueError(f"invalid_rate={self.invalid_rate!r} must lie in [0, 1]")

    @property
    def Nm_per_count(self) -> float:
        """Resolution of the reading (N m per count)."""
        return self.max_torque_Nm / LOAD_MAGNITUDE_MAX


AX12_LOAD = LoadParams()
"""The seed paper's servo's load reading (AX-12A)."""


def valid_load_words(words: np.ndarray) -> np.ndarray:
    """Elementwise validity of load words: integers in 0..:data:`LOAD_MAX_WORD` (a dropout,
    a fraction, NaN or a word with bits above 10 is invalid)."""
    w = np.asarray(words, dtype=np.float64)
    return np.isfinite(w) & (w == np.floor(w)) & (w >= 0) & (w <= LOAD_MAX_WORD)


def load_torque_Nm(words: np.ndarray, params: LoadParams = AX12_LOAD,
                   sign: int = 1) -> np.ndarray:
    """Joint torque (N m, flexion positive) of valid load words: the magnitude's fraction of
    ``max_torque_Nm``, positive for a CCW load; ``sign`` is the mounting's (the
    :class:`Calibration` sign: +1 when counts, i.e. CCW, grow with flexion). Invalid words
    raise ValueError naming the first (the chain's rule decides what replaces them)."""
    w = np.asarray(words, dtype=np.float64)
    ok = valid_load_words(w)
    if not np.all(ok):
        raise ValueError(f"load word {w[~ok].ravel()[0]!r} is invalid (valid: integers "
                         f"0..{LOAD_MAX_WORD})")
    if sign not in (1, -1):
        raise ValueError(f"sign={sign!r} must be +1 or -1")
    wi = w.astype(np.int64)
    direction = np.where(wi & LOAD_DIRECTION_BIT, -1.0, 1.0)
    return sign * direction * (wi & LOAD_MAGNITUDE_MAX) * params.Nm_per_count
