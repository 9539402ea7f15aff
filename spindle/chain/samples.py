"""What both backends of the chain hand out and take in: the sample types and the checks of a
push's inputs, outside either implementation (the numpy chain in :mod:`spindle.chain.batch`
and :mod:`spindle.chain.arm`, the C chain in :mod:`spindle.native.chain`).

:class:`~spindle.chain.config.ArmSample` is one arm's output, :class:`BatchSample` many arms'
(the same fields with a leading axis of arms).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from spindle import core
from spindle.chain.config import SCALAR_OUTPUTS, ArmSample, real_array, real_number

_PER_MUSCLE = tuple(f.name for f in fields(ArmSample) if f.name not in
                    ("accepted", *SCALAR_OUTPUTS))


@dataclass(frozen=True)
class BatchSample:
    """The outputs of every arm after one push: :class:`~spindle.chain.config.ArmSample`'s
    fields with a leading axis of arms.

    Attributes:
        t_s, accepted, counts, counts_filtered, angle_deg, torque_Nm: (n_arms,) each.
        length_L0, velocity_L0_s, acceleration_L0_s2, template_L0, gamma_static_pps,
            gamma_dynamic_pps, ia_pps, ii_pps, force_N, ib_pps: (n_arms, 2) each, muscles
            in ``MUSCLES`` order.

    An arm whose sample was rejected, or that got none, repeats its last output with
    ``accepted`` False. The arrays are read-only (the chain shares them with its state).
    """

    t_s: np.ndarray
    accepted: np.ndarray
    counts: np.ndarray
    counts_filtered: np.ndarray
    angle_deg: np.ndarray
    torque_Nm: np.ndarray
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

    def arm(self, k: int) -> ArmSample:
        """Arm ``k``'s output as the single chain's :class:`ArmSample`."""
        return ArmSample(
            t_s=float(self.t_s[k]), accepted=bool(self.accepted[k]),
            counts=float(self.counts[k]), counts_filtered=float(self.counts_filtered[k]),
            angle_deg=float(self.angle_deg[k]), torque_Nm=float(self.torque_Nm[k]),
            **{name: getattr(self, name)[k].copy() for name in _PER_MUSCLE})



def lengths_valid(L: np.ndarray) -> np.ndarray:
    """Per row of (..., 2): 2 finite lengths within the spindle's range."""
    lo, hi = core.LENGTH_RANGE_L0
    # NaN and infinities fail one of the comparisons
    return ((L >= lo) & (L <= hi)).all(axis=-1)


def checked_lengths(length_L0: np.ndarray) -> np.ndarray | None:
    """A copy of ``length_L0`` if it is 2 finite lengths within the spindle's range, else None."""
    L = real_array(length_L0)
    if L.shape != (2,) or not bool(lengths_valid(L)):
        return None
    return L.copy()


def checked_angle(angle_deg: float) -> float:
    """``angle_deg`` as a float; ``ValueError`` unless it is one finite real number."""
    angle = real_number(angle_deg)
    if not math.isfinite(angle):
        raise ValueError(f"angle_deg={angle_deg!r} must be a finite real number")
    return angle


def block_inputs(name: str, t_s: np.ndarray, signal: np.ndarray,
                 sample_shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(times, signal) of a block push as real arrays (NaN for anything else), shapes checked."""
    t = real_array(t_s)
    x = real_array(signal)
    if t.ndim != 1 or x.shape != (t.size, *sample_shape):
        raise ValueError(f"{name} has shape {x.shape} and t_s {t.shape}; expected "
                         f"{(t.size, *sample_shape)} for (k,) times")
    return t, x


def check_loads(push: str, load: object, shape: tuple[int, ...]) -> np.ndarray | None:
    """The load words of a block or trace as a float array of ``shape`` (NaN for non-real
    entries: invalid words), None for no load; ValueError for a wrong shape or a load with
    another entry point than ``push_counts``."""
    if load is None:
        return None
    if push != "push_counts":
        raise ValueError(f"load words come with encoder counts (push_counts), not {push}")
    words = real_array(load)
    if words.shape != shape:
        raise ValueError(f"load has shape {words.shape}; expected {shape} like t_s")
    return words


def stack_samples(samples: list[ArmSample], like: ArmSample) -> dict[str, np.ndarray]:
    """The fields of ``samples`` stacked on axis 0 (shaped as ``like``'s when there are none)."""
    return {f.name: np.array([getattr(sample, f.name) for sample in samples]) if samples
            else np.empty((0, *np.shape(getattr(like, f.name))),
                          dtype=np.asarray(getattr(like, f.name)).dtype)
            for f in fields(ArmSample)}
