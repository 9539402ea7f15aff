"""The counter-based generator of the stochastic encoder, written once in numpy (and once in
C, ``stimulation.c``) with the same operations so both give the same bits and the same
doubles.

Draw ``index`` of channel ``channel`` under ``seed`` is a pure function of the three
integers (no stream state): SplitMix64's finaliser (Steele, Lea & Flood 2014, OOPSLA "Fast
splittable pseudorandom number generators") applied as a hash,
``bits = mix(mix(mix(seed) ^ channel) ^ index)``; the uniform is
``((bits >> 12) + 0.5) * 2**-52`` in (0, 1), exact (52 bits and the half fit a
double's 53). The exponential draw ``-log(u)`` uses
:func:`log_unit` below (frexp, then 2 atanh(s) by a fixed Horner series) rather than libm's or
numpy's log, whose last bits differ between libraries: +, -, *, / and frexp round the same in
IEEE 754 doubles everywhere (the C build has no contraction into FMA).
"""

from __future__ import annotations

import numpy as np

MASK64 = (1 << 64) - 1
GOLDEN = np.uint64(0x9E3779B97F4A7C15)
MIX1 = np.uint64(0xBF58476D1CE4E5B9)
MIX2 = np.uint64(0x94D049BB133111EB)
LN2 = 0.6931471805599453
SQRT_HALF = 0.7071067811865476
ATANH_TERMS = 12
"""Terms of 2 atanh(s) = 2 (s + s^3/3 + ...): |s| <= 0.1716, so the 12th term is < 1e-19."""


def mix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's step and finaliser on uint64 (wrapping arithmetic)."""
    z = np.asarray(x, dtype=np.uint64) + GOLDEN
    z = (z ^ (z >> np.uint64(30))) * MIX1
    z = (z ^ (z >> np.uint64(27))) * MIX2
    return z ^ (z >> np.uint64(31))


def draw_bits(seed: int, channel: np.ndarray, index: np.ndarray) -> np.ndarray:
    """64 random bits of draw ``index`` of ``channel`` (arrays broadcast)."""
    with np.errstate(over="ignore"):  # numpy warns on a scalar's wrap-around, which is wanted
        key = mix(np.uint64(seed & MASK64)) ^ np.asarray(channel, dtype=np.uint64)
        return mix(mix(key) ^ np.asarray(index, dtype=np.uint64))


def uniform(seed: int, channel: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Uniform draws in the open interval (0, 1), 52 bits each."""
    bits = draw_bits(seed, channel, index) >> np.uint64(12)
    return (bits.astype(np.float64) + 0.5) * 2.0 ** -52


def log_unit(u: np.ndarray) -> np.ndarray:
    """log(u) for 0 < u <= 1 to ~1 ulp, by operations that round alike in numpy and C."""
    m, e = np.frexp(np.asarray(u, dtype=np.float64))
    low = m < SQRT_HALF
    m = np.where(low, m * 2.0, m)
    e = np.where(low, e - 1, e).astype(np.float64)
    f = m - 1.0
    s = f / (2.0 + f)
    s2 = s * s
    series = np.full_like(s, 1.0 / (2 * ATANH_TERMS - 1))
    for k in range(ATANH_TERMS - 2, -1, -1):
        series = series * s2 + 1.0 / (2 * k + 1)
    return e * LN2 + 2.0 * s * series


def gamma_threshold(seed: int, channel: np.ndarray, draw: np.ndarray,
                    shape: int) -> np.ndarray:
    """Draw number ``draw`` of a gamma(shape, 1/shape) variable (mean 1) per channel: the mean
    of ``shape`` exponentials, draws ``draw * shape`` .. ``draw * shape + shape - 1``, summed
    in that order (as the C loop does)."""
    channel = np.asarray(channel, dtype=np.uint64)[..., None]
    first = np.asarray(draw, dtype=np.uint64)[..., None] * np.uint64(shape)
    logs = log_unit(uniform(seed, channel, first + np.arange(shape, dtype=np.uint64)))
    total = np.zeros(logs.shape[:-1])
    for j in range(shape):
        total = total - logs[..., j]
    return total / shape
