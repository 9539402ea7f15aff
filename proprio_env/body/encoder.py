"""The simulated servo encoder: the noise model of the readings the prosthesis chain gets.

:class:`Encoder` produces what the device would (for the envs, experiments and tests):
quantisation, Gaussian noise before rounding, sample-time jitter and rare invalid readings,
with the figures of an :class:`~spindle.chain.sensor.EncoderParams` (:data:`AX12` by default).
:class:`EncoderBatch` reads many encoders at once (one per env of a vector env) with the same
maths and the same random numbers. The device-side processing of those readings lives in
:mod:`spindle.chain.sensor`.

Random numbers are drawn in chunks of :data:`CHUNK` readings, from two generators spawned from
the encoder's ``rng`` at construction: one for the sample intervals, one for the readings'
noise and glitches. Each stream is consumed in order whatever the interleaving of
:meth:`Encoder.next_sample_time_s` and :meth:`Encoder.read` calls, so an encoder read one value
at a time, in blocks (:meth:`Encoder.read_block`) or inside an :class:`EncoderBatch` gives the
same readings for the same seed.
"""

from __future__ import annotations

import numpy as np

from spindle.chain.sensor import (
    AX12,
    AX12_LOAD,
    INVALID_READING,
    LOAD_DIRECTION_BIT,
    LOAD_MAGNITUDE_MAX,
    Calibration,
    EncoderParams,
    LoadParams,
)

__all__ = ["CHUNK", "Encoder", "EncoderBatch", "LoadSensor", "interp_rows", "interval_chunk",
           "load_readings", "readings"]

CHUNK = 64
"""Readings per chunk of random draws (one generator call per stream every CHUNK readings)."""

_NOISE, _U_INVALID, _U_KIND, _WORD = range(4)
_N_READ = 4


def interval_chunk(rng: np.random.Generator, params: EncoderParams) -> np.ndarray:
    """(CHUNK,) sample intervals (s): the nominal period plus a Gaussian jitter clipped to
    +-40 % of the period (so the readings stay in order)."""
    p = params
    jitter = np.clip(p.jitter_s * rng.standard_normal(CHUNK), -0.4 * p.period_s,
                     0.4 * p.period_s)
    return p.period_s + jitter


def read_chunk(rng: np.random.Generator, params: EncoderParams) -> np.ndarray:
    """(4, CHUNK) per-reading randomness: noise (counts), the uniform deciding a glitch, the
    uniform deciding its kind, and the corrupted word a glitch may return."""
    out = np.empty((_N_READ, CHUNK))
    out[_NOISE] = params.noise_counts * rng.standard_normal(CHUNK)
    out[_U_INVALID:] = rng.random((3, CHUNK))
    out[_WORD] = np.floor(out[_WORD] * 65536.0)
    return out


def readings(angle_deg: np.ndarray, draws: np.ndarray, params: EncoderParams,
             calibration: Calibration) -> np.ndarray:
    """Readings (counts, float) at elbow angles ``angle_deg`` (any shape S) with the
    per-reading randomness ``draws`` (shape (4,) + S, rows as :func:`read_chunk`).

    A valid reading is the calibrated count plus noise, rounded and saturated to
    0..max_count; with probability ``invalid_rate`` the reading is :data:`INVALID_READING`
    or (half of the time) a corrupted 16-bit word.
    """
    x = calibration.counts(angle_deg) + draws[_NOISE]
    valid = np.clip(np.rint(x), 0, params.max_count)
    glitch = np.where(draws[_U_KIND] < 0.5, float(INVALID_READING), draws[_WORD])
    return np.where(draws[_U_INVALID] < params.invalid_rate, glitch, valid)


def interp_rows(t_s: np.ndarray, knots_t_s: np.ndarray, knots_y: np.ndarray) -> np.ndarray:
    """Row-wise linear interpolation: ``t_s`` (n, k) inside rows of increasing ``knots_t_s``
    (n, m); the same arithmetic for one row as for many (the single and the vector env read
    the same angles)."""
    n, m = knots_t_s.shape
    j = np.minimum((knots_t_s[:, None, 1:] <= t_s[:, :, None]).sum(axis=2), m - 2)
    # flat indices: take_along_axis costs ~10x more per call at the envs' sizes
    j += np.arange(0, n * m, m)[:, None]
    kt, ky = knots_t_s.ravel(), knots_y.ravel()
    t0, t1, y0, y1 = kt[j], kt[j + 1], ky[j], ky[j + 1]
    return y0 + (t_s - t0) * ((y1 - y0) / (t1 - t0))


class Encoder:
    """Simulated encoder: jittered sample times and quantised, noisy, occasionally bad readings.

    Args:
        params: the device (:data:`AX12` by default).
        calibration: how the servo is mounted on the elbow (f(x) inverted to make readings).
        rng: a ``numpy.random.Generator`` or a seed: two generators are spawned from it at
            construction (one draw of two seeds), the only source of randomness.
    """

    def __init__(
        self,
        params: EncoderParams = AX12,
        calibration: Calibration | None = None,
        rng: np.random.Generator | int | None = None,
    ) -> None:
        self.params = params
        self.calibration = Calibration(deg_per_count=params.deg_per_count) if (
            calibration is None) else calibration
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        time_seed, read_seed = rng.integers(0, 2**63, size=2)
        self.time_rng = np.random.default_rng(int(time_seed))
        self.read_rng = np.random.default_rng(int(read_seed))
        self._intervals = np.empty(0)
        self._draws = np.empty((_N_READ, 0))

    def interval_chunk(self) -> np.ndarray:
        """The next :data:`CHUNK` sample intervals of this encoder's stream (s)."""
        return interval_chunk(self.time_rng, self.params)

    def read_chunk(self) -> np.ndarray:
        """The next :data:`CHUNK` readings' randomness of this encoder's stream."""
        return read_chunk(self.read_rng, self.params)

    def next_sample_time_s(self, t_s: float) -> float:
        """The time of the reading after one taken at ``t_s`` (nominal period + jitter)."""
        if self._intervals.size == 0:
            self._intervals = self.interval_chunk()
        interval, self._intervals = self._intervals[0], self._intervals[1:]
        return float(t_s + interval)

    def read(self, angle_deg: float) -> int:
        """One reading (counts) of the servo at elbow angle ``angle_deg``.

        Valid readings are integers in 0..max_count (the device saturates at its ends); an
        invalid reading is :data:`INVALID_READING` or a corrupted word (see
        :class:`EncoderParams`).
        """
        return int(self.read_block(np.array([float(angle_deg)]))[0])

    def read_block(self, angle_deg: np.ndarray) -> np.ndarray:
        """Readings (counts, float) at the angles ``angle_deg`` (k,), in order."""
        k = angle_deg.shape[0]
        while self._draws.shape[1] < k:
            self._draws = np.concatenate((self._draws, self.read_chunk()), axis=1)
        draws, self._draws = self._draws[:, :k], self._draws[:, k:]
        return readings(angle_deg, draws, self.params, self.calibration)

    def record(
        self, t_s: np.ndarray, angle_deg: np.ndarray, t_start_s: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Readings of a whole motion: sample times (s) and counts (int64).

        ``angle_deg`` sampled at the (increasing) times ``t_s`` is interpolated linearly at
        each jittered sample time between ``t_start_s`` (default ``t_s[0]``) and ``t_s[-1]``.
        """
        t_s = np.asarray(t_s, dtype=float)
        angle_deg = np.asarray(angle_deg, dtype=float)
        if t_s.ndim != 1 or t_s.shape != angle_deg.shape or t_s.size < 2:
            raise ValueError(
                f"t_s and angle_deg must be 1-D of one length >= 2, got {t_s.shape} and "
                f"{angle_deg.shape}"
            )
        if not (np.all(np.isfinite(t_s)) and np.all(np.diff(t_s) > 0)):
            raise ValueError("t_s must be finite and strictly increasing")
        if not np.all(np.isfinite(angle_deg)):
            raise ValueError("angle_deg must be finite")
        times = [t_s[0] if t_start_s is None else float(t_start_s)]
        while True:
            nxt = self.next_sample_time_s(times[-1])
            if nxt > t_s[-1]:
                break
            times.append(nxt)
        t_samples = np.array(times)
        counts = self.read_block(np.interp(t_samples, t_s, angle_deg))
        return t_samples, counts.astype(np.int64)


class EncoderBatch:
    """``n`` encoders read at once: each keeps its own :class:`Encoder` (its own streams), and
    the bank holds their next random draws in (n, width) buffers with a cursor per encoder,
    so that one env step's readings of every encoder take a few array operations (a Python
    call per encoder only every :data:`CHUNK` readings, to refill).

    Args:
        n: number of encoders.
        params: the device, shared by all.
        window: the most readings one :meth:`step` may need per encoder, plus one.
    """

    def __init__(self, n: int, params: EncoderParams = AX12, window: int = CHUNK) -> None:
        self.n = n
        self.params = params
        self.calibration = Calibration(deg_per_count=params.deg_per_count)
        self.window = int(window)
        width = CHUNK * (-(-self.window // CHUNK) + 1)
        self.encoders: list[Encoder | None] = [None] * n
        self._intervals = np.zeros((n, width))
        self._draws = np.zeros((_N_READ, n, width))
        # per encoder: next unused buffered draw and end of the buffered draws
        self._i_cur = np.zeros(n, dtype=np.int64)
        self._i_end = np.zeros(n, dtype=np.int64)
        self._d_cur = np.zeros(n, dtype=np.int64)
        self._d_end = np.zeros(n, dtype=np.int64)
        self._rows = np.arange(n)[:, None]
        self._ahead = np.arange(self.window)
        self.next_read_s = np.zeros(n)
        self.last_t_s = np.zeros(n)
        self.last_angle_deg = np.zeros(n)

    def reset(self, i: int, t_s: float, angle_deg: float, rng: np.random.Generator) -> None:
        """Encoder ``i`` starts afresh at ``t_s`` with a new :class:`Encoder` spawned from
        ``rng`` (the env's generator); its first reading is one jittered period later."""
        self.encoders[i] = Encoder(self.params, self.calibration, rng=rng)
        self._i_cur[i] = self._i_end[i] = self._d_cur[i] = self._d_end[i] = 0
        self._refill_intervals(i, 1)
        self.next_read_s[i] = t_s + self._intervals[i, 0]
        self._i_cur[i] = 1
        self.last_t_s[i] = t_s
        self.last_angle_deg[i] = angle_deg

    def _encoder(self, i: int) -> Encoder:
        enc = self.encoders[i]
        if enc is None:
            raise RuntimeError(f"encoder {i} read before its reset")
        return enc

    def _refill_intervals(self, i: int, need: int) -> None:
        """At least ``need`` buffered intervals for encoder ``i`` (left-aligned, in order)."""
        enc, buf = self._encoder(i), self._intervals[i]
        left = int(self._i_end[i] - self._i_cur[i])
        buf[:left] = buf[self._i_cur[i]:self._i_end[i]]
        while left < need:
            buf[left:left + CHUNK] = enc.interval_chunk()
            left += CHUNK
        self._i_cur[i], self._i_end[i] = 0, left

    def _refill_draws(self, i: int, need: int) -> None:
        """At least ``need`` buffered readings' draws for encoder ``i``."""
        enc, buf = self._encoder(i), self._draws[:, i]
        left = int(self._d_end[i] - self._d_cur[i])
        buf[:, :left] = buf[:, self._d_cur[i]:self._d_end[i]]
        while left < need:
            buf[:, left:left + CHUNK] = enc.read_chunk()
            left += CHUNK
        self._d_cur[i], self._d_end[i] = 0, left

    def step(self, t_s: np.ndarray, angle_deg: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The readings of one env step: every reading due up to the last physics time.

        Args:
            t_s: (n, F) physics times of the step (increasing; the step started at the
                previous step's last time, or the reset time).
            angle_deg: (n, F) elbow angle at those times; a reading's angle is interpolated
                linearly between them.

        Returns:
            ``read_t_s`` (n, K), ``counts`` (n, K) and ``n_samples`` (n,): encoder i read
            ``n_samples[i]`` times; the entries past that are padding (NaN).
        """
        n, w, rows = self.n, self.window, self._rows
        end = t_s[:, -1]
        for i in np.flatnonzero(self._i_end - self._i_cur < w - 1).tolist():
            self._refill_intervals(i, w - 1)
        # reading times: cumulated intervals from the next reading (sequential sums, as a
        # single encoder adds one interval at a time)
        times = np.empty((n, w))
        times[:, 0] = self.next_read_s
        times[:, 1:] = self._intervals[rows, self._i_cur[:, None] + self._ahead[:w - 1]]
        np.cumsum(times, axis=1, out=times)
        due = times <= end[:, None]
        n_samples = due.sum(axis=1)
        if np.any(n_samples >= w):
            raise RuntimeError(f"more than {w - 1} encoder readings in one env step")
        k = max(int(n_samples.max()), 1)
        self.next_read_s = times[rows[:, 0], n_samples]
        self._i_cur += n_samples
        for i in np.flatnonzero(self._d_end - self._d_cur < n_samples).tolist():
            self._refill_draws(i, int(n_samples[i]))
        due = due[:, :k]
        read_t = np.where(due, times[:, :k], np.nan)
        knots_t = np.concatenate((self.last_t_s[:, None], t_s), axis=1)
        knots_a = np.concatenate((self.last_angle_deg[:, None], angle_deg), axis=1)
        angles = interp_rows(np.where(due, read_t, end[:, None]), knots_t, knots_a)
        draws = self._draws[:, rows, self._d_cur[:, None] + self._ahead[:k]]
        counts = readings(angles, draws, self.params, self.calibration)
        counts[~due] = np.nan
        self._d_cur += n_samples
        self.last_t_s = end.copy()
        self.last_angle_deg = angle_deg[:, -1].copy()
        return read_t, counts, n_samples


# -- the load reading (the force sense) --------------------------------------------------------
def load_readings(torque_Nm: np.ndarray, draws: np.ndarray, params: LoadParams = AX12_LOAD,
                  sign: int = 1) -> np.ndarray:
    """Load words (float) for joint torques ``torque_Nm`` (N m, flexion positive; any shape S)
    with per-reading randomness ``draws`` ((4,) + S, rows as :func:`read_chunk` with the noise
    row in counts of ``params``).

    A valid word is the torque's magnitude in counts plus noise, rounded and saturated to
    0..1023, with bit 10 set for a CW load (flexion is CCW for ``sign`` +1); the direction
    is the noisy torque's sign. With probability ``invalid_rate`` the word is
    :data:`INVALID_READING` or (half of the time) a corrupted 16-bit word.
    """
    counts = sign * np.asarray(torque_Nm, dtype=float) / params.Nm_per_count + draws[_NOISE]
    magnitude = np.clip(np.rint(np.abs(counts)), 0, LOAD_MAGNITUDE_MAX)
    valid = magnitude + np.where(counts < 0, float(LOAD_DIRECTION_BIT), 0.0)
    glitch = np.where(draws[_U_KIND] < 0.5, float(INVALID_READING), draws[_WORD])
    return np.where(draws[_U_INVALID] < params.invalid_rate, glitch, valid)


class LoadSensor:
    """The servo's simulated load reading: quantised, noisy, occasionally invalid words.

    Its own generator (spawned from ``rng``), so adding load readings leaves an
    :class:`Encoder`'s angle readings unchanged for the same seed.
    """

    def __init__(self, params: LoadParams = AX12_LOAD, sign: int = 1,
                 rng: np.random.Generator | int | None = None) -> None:
        self.params = params
        self.sign = sign
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self._noise = EncoderParams(noise_counts=params.noise_counts,
                                    invalid_rate=params.invalid_rate)
        self._draws = np.empty((_N_READ, 0))

    def read_block(self, torque_Nm: np.ndarray) -> np.ndarray:
        """Load words (float) at the torques ``torque_Nm`` (k,), in order."""
        torque = np.asarray(torque_Nm, dtype=float)
        if torque.ndim != 1 or not np.all(np.isfinite(torque)):
            raise ValueError("torque_Nm must be a finite 1-D array")
        k = torque.shape[0]
        while self._draws.shape[1] < k:
            self._draws = np.concatenate((self._draws, read_chunk(self.rng, self._noise)),
                                         axis=1)
        draws, self._draws = self._draws[:, :k], self._draws[:, k:]
        return load_readings(torque, draws, self.params, self.sign)
