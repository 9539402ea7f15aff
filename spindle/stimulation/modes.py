"""The encoding modes (rate -> pulse rate and amplitude) and their settings.

======================  =========================================================================
mode                    what it does
======================  =========================================================================
``"frequency"``         deterministic integrate-and-fire: pulse rate = afferent rate, amplitude
                        fixed at ``max_uA``; a pulse each time the rate's integral crosses one
``"stochastic"``        gamma-renewal (Poisson for ``gamma_shape = 1``) with a dead time, same
                        mean rate, amplitude ``max_uA``; counter-based, seeded draws
``"amplitude"``         fixed carrier rate, amplitude from threshold to maximum with the rate
``"biomimetic"``        pulse rate and amplitude both from the rate and its rate of change
======================  =========================================================================

Biomimetic mapping. After Okorokova et al. 2018 (J Neural Eng 15:066033), whose encoding
model makes pulse frequency follow the afferent population's firing and amplitude its
recruitment, both peaking at transients, and George et al. 2019 (Sci Robot 4:eaax2352), whose
biomimetic encodings add the sensor's rate of change to its level. With the level
``s = clip(r / full_scale_pps, 0, 1)`` and the change ``d = clip(|dr/dt| /
full_scale_change_pps_s, 0, 1)`` (backward difference between samples)::

    pulse rate = max_rate_pps * clip(rate_level * s + rate_change * d, 0, 1)
    amplitude  = threshold + (max - threshold) * clip(amp_level * s + amp_change * d, 0, 1)

The stochastic mode follows the asynchronous, irregular trains Formento et al. 2020 (J Neural
Eng 17:046019) argue are more natural than regular ones: after each pulse the channel waits
the dead time ``tau``, then integrates ``r / (1 - r tau)`` up to a gamma(k, 1/k) threshold
(mean 1), so a constant rate ``r`` gives intervals ``tau + gamma(k, 1 / (k r'))`` of mean
``1 / r`` (time rescaling: the same law holds for varying rates in rescaled time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from spindle.stimulation.checks import is_real


@dataclass(frozen=True)
class Mode:
    """One row of :data:`MODES`: a name, its code in ``proprio.h`` and what it varies."""

    name: str
    code: int
    stochastic: bool
    varies_rate: bool
    varies_amplitude: bool


MODES: dict[str, Mode] = {m.name: m for m in (
    Mode("frequency", 0, stochastic=False, varies_rate=True, varies_amplitude=False),
    Mode("stochastic", 1, stochastic=True, varies_rate=True, varies_amplitude=False),
    Mode("amplitude", 2, stochastic=False, varies_rate=False, varies_amplitude=True),
    Mode("biomimetic", 3, stochastic=False, varies_rate=True, varies_amplitude=True),
)}
"""The modes by name (codes are ``PS_STIM_MODE_*`` of ``proprio.h``)."""

MAX_GAMMA_SHAPE = 16
MAX_SEED = (1 << 64) - 1


@dataclass(frozen=True)
class EncoderParams:
    """Settings of the encoding (one set for every channel).

    Attributes:
        mode: a key of :data:`MODES`.
        full_scale_pps: afferent rate at which amplitude (and the biomimetic level) saturate.
        full_scale_change_pps_s: |dr/dt| at which the biomimetic change term saturates.
        carrier_pps: the amplitude mode's pulse rate (<= the limits' ``max_rate_pps``).
        rate_level, rate_change, amp_level, amp_change: the biomimetic weights (>= 0).
        gamma_shape: the stochastic intervals' gamma shape k (1: Poisson), 1..16.
        dead_time_s: the stochastic mode's dead time (>= each channel's minimum interval;
            ``max_rate_pps * dead_time_s < 1``).
        seed: the stochastic draws' seed (0 .. 2**64 - 1).

    Defaults (assumed): full scale 100 pps (the demo's human Ia peaks near 50 pps), 2000
    pps/s, carrier 100 pps, weights 0.5/0.5 (rate) and 1.0/0.5 (amplitude), Poisson, 2 ms
    dead time (a human afferent's absolute refractory period is ~1 ms), seed 0.
    """

    mode: str = "frequency"
    full_scale_pps: float = 100.0
    full_scale_change_pps_s: float = 2000.0
    carrier_pps: float = 100.0
    rate_level: float = 0.5
    rate_change: float = 0.5
    amp_level: float = 1.0
    amp_change: float = 0.5
    gamma_shape: int = 1
    dead_time_s: float = 2e-3
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode={self.mode!r} is not one of {sorted(MODES)}")
        for name in ("full_scale_pps", "full_scale_change_pps_s", "carrier_pps"):
            value = getattr(self, name)
            if not (is_real(value) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name}={value!r} must be a finite number > 0")
        for name in ("rate_level", "rate_change", "amp_level", "amp_change"):
            value = getattr(self, name)
            if not (is_real(value) and math.isfinite(value) and 0 <= value <= 1e3):
                raise ValueError(f"{name}={value!r} must be a finite number in [0, 1000]")
        if not (is_real(self.dead_time_s) and math.isfinite(self.dead_time_s)
                and 0 < self.dead_time_s <= 1.0):
            raise ValueError(f"dead_time_s={self.dead_time_s!r} must be in (0, 1] s")
        for name, hi in (("gamma_shape", MAX_GAMMA_SHAPE), ("seed", MAX_SEED)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not \
                    (0 if name == "seed" else 1) <= value <= hi:
                raise ValueError(f"{name}={value!r} must be an int in "
                                 f"[{0 if name == 'seed' else 1}, {hi}]")

    @property
    def code(self) -> int:
        return MODES[self.mode].code
