"""Sub-stepping between samples: how many internal steps, and the length at each.

A sample interval ``dt`` is split into the fewest equal internal steps no longer than the
integrator's step (:func:`substeps`). The length between samples follows a Hermite curve
through the samples and their derivatives (:func:`hermite_curve`), held inside the spindle's
valid range and speed limit (:func:`substep_lengths`). ``spindle.simulate`` (numpy and C) and
the prosthesis chain use these.
"""

from __future__ import annotations

import math

import numpy as np

from spindle import core


def substeps(dt_s: float, step_s: float) -> int:
    """Number of equal internal steps, each at most ``step_s``, that make up ``dt_s``."""
    return max(1, math.ceil(dt_s / step_s * (1 - 1e-12)))


def substep_lengths(L: np.ndarray, derivatives: list[np.ndarray], k: int, dt: float,
                    i0: int = 1, i1: int | None = None) -> tuple[np.ndarray, int]:
    """The length at the end of every internal step of sample intervals i0 .. i1-1 (interval
    i ends on sample i), shape ((i1 - i0)*k, n), and how many of them the limits changed.

    Sub-step j of an interval is the Hermite curve at fraction j/k (linear without
    ``derivatives``); step k ends on the sample itself. The curve can overshoot where valid
    samples lie near a range end or move near the speed limit, so each sub-step length is
    clipped to the valid range and to where it stays within MAX_SPEED_L0_S (less 1e-9, so
    that rounding never crosses the limit) both of the previous sub-step and of the sample
    that ends the interval: the clipped path is never faster than the limit and always lands
    on that sample. Inside those limits the curve is untouched (bit for bit). Both backends
    use these lengths.
    """
    i1 = L.shape[0] if i1 is None else i1
    start, end = L[i0 - 1:i1 - 1], L[i0:i1]
    out = np.empty((i1 - i0, k, L.shape[1]))
    out[:, k - 1] = end
    if k == 1:
        return out.reshape(-1, L.shape[1]), 0
    pairs = [(d[i0 - 1:i1 - 1], d[i0:i1]) for d in derivatives]
    lo_range, hi_range = core.LENGTH_RANGE_L0
    # each sub-step moves at most `reach`; samples that already move at the limit (within
    # the margin) keep their own pace, so that the band below never closes
    reach = np.maximum(core.MAX_SPEED_L0_S * (1.0 - 1e-9) * dt / k, np.abs(end - start) / k)
    previous = start
    changed = 0
    for j in range(1, k):
        value = hermite_curve(j / k, start, end, pairs, dt)
        left = reach * (k - j)  # what the remaining sub-steps can still cover
        lo = np.maximum(np.maximum(previous - reach, end - left), lo_range)
        hi = np.minimum(np.minimum(previous + reach, end + left), hi_range)
        clipped = np.minimum(np.maximum(value, lo), hi)
        changed += int(np.count_nonzero(clipped != value))
        out[:, j - 1] = clipped
        previous = clipped
    return out.reshape(-1, L.shape[1]), changed


def bounded_hermite_length(s, start: np.ndarray, end: np.ndarray, v_start: np.ndarray,
                           v_end: np.ndarray, dt, previous: np.ndarray, reach,
                           left) -> np.ndarray:
    """A chain's sub-step length: the cubic Hermite curve at fraction ``s`` of a sample
    interval of ``dt`` (lengths and velocities at its ends), clipped in turn to within
    ``reach`` of the previous sub-step's length ``previous``, to within ``left`` of ``end``
    (what the remaining sub-steps can still cover: a bridge whose end velocities disagree
    would otherwise overshoot both) and to the spindle's valid range. ``s``, ``dt``, ``reach``
    and ``left`` are floats or arrays broadcasting against the lengths (``dt`` is not
    modified). ``ArmChain`` and ``ArmChainBatch`` (sample by sample and a block at once)
    step their spindles through these."""
    curve = hermite_curve(s, start, end, [(v_start, v_end)],
                          dt.copy() if isinstance(dt, np.ndarray) else dt)
    curve = np.minimum(np.maximum(curve, previous - reach), previous + reach)
    curve = np.minimum(np.maximum(curve, end - left), end + left)
    lo, hi = core.LENGTH_RANGE_L0
    return np.minimum(np.maximum(curve, lo), hi)


def hermite_curve(s: float, start: np.ndarray, end: np.ndarray,
                  derivatives: list[tuple[np.ndarray, np.ndarray]], dt: float) -> np.ndarray:
    """The Hermite curve of an interval of ``dt`` at fraction ``s``: through the values
    ``start`` and ``end`` and, for each pair (at start, at end) in ``derivatives``, the first
    (then second) derivatives; linear without them."""
    w = hermite_weights(s, len(derivatives))
    value = w[0] * start + w[1] * end
    scale = dt
    for q, (d0, d1) in enumerate(derivatives):
        value = value + scale * (w[2 + 2 * q] * d0 + w[3 + 2 * q] * d1)
        scale *= dt
    return value


def hermite_weights(s: float, order: int) -> np.ndarray:
    """Weights of (L0, L1, dt*v0, dt*v1, dt^2*a0, dt^2*a1) at fraction s of an interval.

    order 0: linear; 1: cubic Hermite (values and first derivatives); 2: quintic Hermite
    (values, first and second derivatives).
    """
    if order == 0:
        return np.array([1 - s, s])
    if order == 1:
        s2, s3 = s * s, s * s * s
        return np.array([2 * s3 - 3 * s2 + 1, -2 * s3 + 3 * s2, s3 - 2 * s2 + s, s3 - s2])
    s2, s3, s4, s5 = s**2, s**3, s**4, s**5
    return np.array([
        1 - 10 * s3 + 15 * s4 - 6 * s5,
        10 * s3 - 15 * s4 + 6 * s5,
        s - 6 * s3 + 8 * s4 - 3 * s5,
        -4 * s3 + 7 * s4 - 3 * s5,
        0.5 * (s2 - 3 * s3 + 3 * s4 - s5),
        0.5 * (s3 - 2 * s4 + s5),
    ])


def slew_limited(L: np.ndarray, last: np.ndarray, limit, axis: int = 0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The slew limit of a chain and a spindle bank: each length of ``L`` moved by at most
    ``limit`` (a float, or an array broadcasting against ``L``) from the one before it along
    ``axis`` (the first from ``last``, ``L`` without that axis). Returns the limited lengths
    and where the limit acted. A length within the limit is kept as it is (bit for bit)."""
    steps = np.diff(L, axis=axis, prepend=np.expand_dims(last, axis))
    with np.errstate(invalid="ignore"):
        if not bool(np.any(np.abs(steps) > limit)):  # one check, not one per step
            return L, np.zeros(L.shape, dtype=bool)
    L = np.moveaxis(L, axis, 0)
    limit = np.moveaxis(np.broadcast_to(limit, np.moveaxis(L, 0, axis).shape), axis, 0)
    out = np.empty_like(L)
    hit = np.zeros(L.shape, dtype=bool)
    previous = last
    for q in range(L.shape[0]):
        change = L[q] - previous
        hit[q] = np.abs(change) > limit[q]
        out[q] = np.where(hit[q], previous + np.clip(change, -limit[q], limit[q]), L[q])
        previous = out[q]
    return np.moveaxis(out, 0, axis), np.moveaxis(hit, 0, axis)
