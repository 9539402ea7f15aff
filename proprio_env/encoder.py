"""The simulated servo encoder: the noise model of the readings the prosthesis chain gets.

:class:`Encoder` produces what the device would (for the envs, experiments and tests):
quantisation, Gaussian noise before rounding, sample-time jitter and rare invalid readings,
with the figures of an :class:`~spindle.chain.sensor.EncoderParams` (:data:`AX12` by default).
The device-side processing of those readings lives in :mod:`spindle.chain.sensor`.
"""

from __future__ import annotations

import numpy as np

from spindle.chain.sensor import AX12, INVALID_READING, Calibration, EncoderParams

__all__ = ["Encoder"]


class Encoder:
    """Simulated encoder: jittered sample times and quantised, noisy, occasionally bad readings.

    Args:
        params: the device (:data:`AX12` by default).
        calibration: how the servo is mounted on the elbow (f(x) inverted to make readings).
        rng: a ``numpy.random.Generator`` or a seed; the only source of randomness.
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
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)

    def next_sample_time_s(self, t_s: float) -> float:
        """The time of the reading after one taken at ``t_s`` (nominal period + jitter)."""
        p = self.params
        jitter = 0.0
        if p.jitter_s > 0:
            jitter = float(np.clip(self.rng.normal(0.0, p.jitter_s),
                                   -0.4 * p.period_s, 0.4 * p.period_s))
        return t_s + p.period_s + jitter

    def read(self, angle_deg: float) -> int:
        """One reading (counts) of the servo at elbow angle ``angle_deg``.

        Valid readings are integers in 0..max_count (the device saturates at its ends); an
        invalid reading is :data:`INVALID_READING` or a corrupted word (see
        :class:`EncoderParams`).
        """
        p = self.params
        if p.invalid_rate > 0 and self.rng.random() < p.invalid_rate:
            if self.rng.random() < 0.5:
                return INVALID_READING
            return int(self.rng.integers(0, 65536))
        x = float(self.calibration.counts(angle_deg))
        if p.noise_counts > 0:
            x += self.rng.normal(0.0, p.noise_counts)
        return int(np.clip(np.rint(x), 0, p.max_count))

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
        angles = np.interp(t_samples, t_s, angle_deg)
        counts = np.array([self.read(a) for a in angles], dtype=np.int64)
        return t_samples, counts
