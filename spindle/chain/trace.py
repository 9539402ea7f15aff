"""A whole trace through the chain: :func:`run_chain` and its result, :class:`ChainTrace`."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from spindle import number_rule
from spindle.chain.config import MUSCLES, ArmSample, ChainConfig, real_array
from spindle.chain.factory import make_chain
from spindle.chain.length_model import LengthFits
from spindle.chain.samples import checked_lengths
from spindle.chain.sensor import is_valid_reading


@dataclass(frozen=True)
class ChainTrace:
    """Every signal of a batch run; arrays have the samples on axis 0, muscles on axis 1.

    Fields are those of :class:`ArmSample` stacked over samples, plus the final counters.
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
    counters: dict[str, int]

    def columns(self) -> dict[str, np.ndarray]:
        """Flat named columns (per-muscle signals split as ``BRA_ia_pps`` ...), e.g. for CSV."""
        out: dict[str, np.ndarray] = {}
        for f in fields(ArmSample):
            value = getattr(self, f.name)
            if value.ndim == 2:
                for k, muscle in enumerate(MUSCLES):
                    out[f"{muscle}_{f.name}"] = value[:, k]
            else:
                out[f.name] = value
        return out


def run_chain(
    t_s: np.ndarray,
    *,
    counts: np.ndarray | None = None,
    angle_deg: np.ndarray | None = None,
    length_L0: np.ndarray | None = None,
    intended_angle_deg: np.ndarray | None = None,
    load: np.ndarray | None = None,
    config: ChainConfig | None = None,
    fits: LengthFits | None = None,
) -> ChainTrace:
    """Run the chain over a whole trace; exactly what the chain does sample by sample.

    The chain is ``make_chain(config, fits)`` (numpy or C, as ``config.backend`` says); the
    trace goes through its ``run_trace`` (:class:`~spindle.chain.config.Chain`).

    Give the samples' times ``t_s`` (T,) and one of ``counts`` (T,) encoder readings,
    ``angle_deg`` (T,) elbow angles or ``length_L0`` (T, 2) fibre lengths. The arm starts at
    rest at the first sample that is valid (its output is that rest state, its angle clamped to
    the length model's range and counted like any other sample's); the other samples
    are pushed in order (bad ones are handled by the documented rules). ``intended_angle_deg``
    (T,) switches the fusimotor template to the intended motion. ``load`` (T,) the servo's
    load words read beside ``counts`` (only with counts; None: no load, Ib at rest at zero
    force): the first sample's starts the tendon organs at rest (an invalid one at zero
    torque, counted ``invalid_load``), the others follow the load rules.
    """
    given = [x is not None for x in (counts, angle_deg, length_L0)]
    if sum(given) != 1:
        raise ValueError("give exactly one of counts, angle_deg or length_L0")
    t = real_array(t_s)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t_s must be a non-empty 1-D array, got shape {t.shape}")
    signal = real_array(next(x for x in (counts, angle_deg, length_L0) if x is not None))
    want = (t.size, 2) if length_L0 is not None else (t.size,)
    if signal.shape != want:
        raise ValueError(f"the signal has shape {signal.shape}, expected {want} for t_s "
                         f"{t.shape}")
    intended = None
    if intended_angle_deg is not None:
        intended = _intended_angles(intended_angle_deg)
        if intended.shape != t.shape:
            raise ValueError(f"intended_angle_deg has shape {intended.shape}, expected {t.shape}")

    words = None
    if load is not None:
        if counts is None:
            raise ValueError("load words come with encoder counts: give counts with load")
        words = real_array(load)
        if words.shape != t.shape:
            raise ValueError(f"load has shape {words.shape}, expected {t.shape}")

    chain = make_chain(config, fits)
    start = _first_valid(t, signal, counts is not None, length_L0 is not None, chain)
    if counts is not None:
        chain.reset(float(chain.config.calibration.angle_deg(signal[start])), t[start],
                    load=None if words is None else words[start])
        push = "push_counts"
    elif angle_deg is not None:
        chain.reset(signal[start], t[start])
        push = "push_angle"
    else:
        lo, hi = chain.angle_range_deg
        chain.reset(0.5 * (lo + hi), t[start], length_L0=signal[start])
        push = "push_lengths"
    first = chain.last
    rest = chain.run_trace(push, t[start + 1:], signal[start + 1:],
                           None if intended is None else intended[start + 1:],
                           None if words is None else words[start + 1:])
    stacked = {
        f.name: np.concatenate([np.array([getattr(first, f.name)] * (start + 1)),
                                rest[f.name]]) for f in fields(ArmSample)
    }
    stacked["accepted"][:start] = False
    return ChainTrace(**stacked, counters=dict(chain.counters))


def _intended_angles(value: object) -> np.ndarray:
    """``run_chain``'s intended angles as floats: real numbers, NaN for the measured motion."""
    why = "must hold real angles in deg (NaN: the measured motion)"
    try:
        intended = number_rule.real_array("intended_angle_deg", value)
    except number_rule.NumberError as exc:
        raise number_rule.NumberError(f"intended_angle_deg {why}: {exc}") from None
    if np.isinf(intended).any():
        raise ValueError(f"intended_angle_deg {why}, got an infinite one")
    return intended


def _first_valid(t, signal, is_counts, is_lengths, chain) -> int:
    for i in range(t.size):
        if not np.isfinite(t[i]):
            continue
        if is_counts:
            ok = is_valid_reading(signal[i], chain.config.encoder.max_count)
        elif is_lengths:
            ok = checked_lengths(signal[i]) is not None
        else:
            ok = bool(np.isfinite(signal[i]))
        if ok:
            return i
    raise ValueError("the trace holds no valid sample to start from")
