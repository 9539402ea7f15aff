"""Parameters of the Lin & Crago (2002) Golgi tendon organ (Ib) model, with presets.

The model (Lin C.-C.K., Crago P.E. (2002) "Neural and mechanical contributions to the stretch
reflex: a model synthesis", Ann Biomed Eng 30:54-67) turns tendon force F (N) into the
aggregate Ib rate of a muscle's tendon organs in three stages:

    r = G1 * ln(F+ / G2 + 1)                       log nonlinearity (pps), F+ = max(F, 0)
    tau * dx/dt = r - x                            first-order low-pass
    Ib = max(0, y),  Y(s) = H(s) X(s),  H(s) = (b2 s^2 + b1 s + b0) / (s^2 + a1 s + a0)

with H(0) = b0 / a0 = 1, so that at rest Ib = r: G1 is the static gain in pps and G2 the force
at which the log bends. Where each constant comes from (``docs/gto.md`` has the full story):

- G1 = 60 pps, G2 = 4 N: the cat preset, the OpenSim afferent plugin's ``Lin02GolgiTendonOrgan``
  (``Gg = 60 pulses/s``, ``Gf = 4 N``); myogen's GTO keeps G2 = 4 N.
- b = (1.7, 2.58, 0.4), a = (2.2, 0.4): the transfer function both published implementations
  encode. myogen's difference equation (``_gto.pyx``) is the bilinear transform of exactly this
  H(s) (its coefficients decode to these six numbers); the OpenSim plugin integrates
  40 * H(s) (numerator 68, 103.2, 16), a DC gain of 40 that puts its static rate 40 x above its
  own log stage. Both share the poles (-0.2, -2 s^-1) and zeros; unit DC gain is the form in
  which G1 keeps its stated meaning (pps), so it is the one taken here.
- tau = 10 ms: the OpenSim plugin's ``lpf_tau`` default (myogen has no low-pass).
- HUMAN: G1 = 40 pps, myogen's human default (which it sources from E. Elias's thesis, p. 83,
  and Aniss et al. 1990's human GTO data); the dynamics are the cat's (no human fit found).

The force scale G2 of a muscle follows one documented rule (:func:`force_scales_N`): the
preset's G2 is for a muscle of maximum isometric force ``reference_max_force_N``, and a muscle
of maximum force F_max gets G2 * F_max / reference_max_force_N, so the log bends at the same
fraction of every muscle's strength.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

ARM26_MAX_ISOMETRIC_FORCE_N = {"BRA": 987.26, "TRImed": 624.3}
"""``max_isometric_force`` (N) of the Arm26 model's BRA and TRImed (Thelen2003Muscle), read from
``/work/shared/reference/opensim/arm26.osim`` (987.25999999999999 and 624.29999999999995)."""

MAX_FORCE_N = 1.0e5
"""Largest tendon force accepted (N): 10x any human tendon's (the Achilles' ~ 10 kN). A larger
finite value is an input error (a unit slip, a diverged simulation), refused with ValueError
rather than turned into a rate."""

MIN_FORCE_SCALE_N = 1.0e-6
"""Smallest force scale G2 accepted (N). G2 sets where the log bends; real ones are newtons
(4 N for the cat soleus, 114-180 N for Arm26's elbow muscles; a 0.2 N mouse muscle's would be
0.04 N). The limit keeps MAX_FORCE_N / G2 (at most 1e11, log1p 25.3) far from overflow: below
~5.6e-304 N the ratio was infinite and the rate NaN. A smaller G2 is refused with ValueError
(``PS_ERR_CONFIG`` in C)."""

MAX_STEP_S = 0.1
"""Longest step accepted (s). The step is exact and stable for any h; the limit only refuses
a time in the wrong unit (1 ms passed as 1). Accuracy within 0.1 pps RMS is measured up to
10 ms (``tests/test_tendon_organ.py``; 0.13 pps at 20 ms)."""


def check_step(dt_s: object) -> float:
    """``dt_s`` as a float, or ValueError (TypeError for a non-number) naming it and the
    limit."""
    try:
        h = float(dt_s)
    except (TypeError, ValueError):
        raise TypeError(f"dt_s={dt_s!r} must be a number of seconds") from None
    if not (np.isfinite(h) and 0.0 < h <= MAX_STEP_S):
        raise ValueError(f"dt_s={dt_s!r} must be finite and in (0, {MAX_STEP_S}] s")
    return h


def check_force_scales(force_scale_N: object, n: int | None = None) -> np.ndarray:
    """``force_scale_N`` (N) as a float64 array, (n,) when ``n`` is given (a scalar is
    broadcast), or ValueError naming the value and the limits: finite and at least
    :data:`MIN_FORCE_SCALE_N`."""
    g = np.asarray(force_scale_N, dtype=np.float64)
    if n is not None and g.shape != (n,):
        try:
            g = np.broadcast_to(g, (n,))
        except ValueError:
            raise ValueError(f"force_scale_N has shape {g.shape}; expected a scalar or "
                             f"({n},)") from None
    if g.size and not (g.min() >= MIN_FORCE_SCALE_N and g.max() < np.inf):  # NaN fails both
        raise ValueError(f"force_scale_N={force_scale_N!r} must be finite and at least "
                         f"MIN_FORCE_SCALE_N={MIN_FORCE_SCALE_N} N")
    return g


@dataclass(frozen=True)
class TendonOrganParams:
    """Constants of the Lin & Crago (2002) GTO model (see the module docstring).

    Attributes:
        gain_pps: G1, the static gain of the log stage (pps).
        force_scale_N: G2 for a muscle of maximum force ``reference_max_force_N`` (N).
        reference_max_force_N: the maximum isometric force G2 belongs to (N).
        tau_lowpass_s: the low-pass time constant (s).
        num: (b2, b1, b0) of H(s); den: (a1, a0) of H(s) (monic, s^-1 and s^-2 units).
    """

    gain_pps: float = 60.0
    force_scale_N: float = 4.0
    reference_max_force_N: float = 22.0
    tau_lowpass_s: float = 0.01
    num: tuple[float, float, float] = (1.7, 2.58, 0.4)
    den: tuple[float, float] = (2.2, 0.4)
    name: str = "custom"

    def __post_init__(self) -> None:
        scalars = ("gain_pps", "force_scale_N", "reference_max_force_N", "tau_lowpass_s")
        for field in scalars:
            value = getattr(self, field)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{field}={value!r} must be finite and > 0")
        check_force_scales(self.force_scale_N)
        if len(self.num) != 3 or len(self.den) != 2:
            raise ValueError(f"num={self.num!r} needs 3 and den={self.den!r} 2 coefficients")
        if not all(np.isfinite(c) for c in (*self.num, *self.den)):
            raise ValueError(f"num={self.num!r}, den={self.den!r} must be finite")
        a1, a0 = self.den
        if not (a1 > 0 and a0 > 0):
            raise ValueError(f"den={self.den!r}: a1 > 0 and a0 > 0 are needed for stable poles")
        if self.num[2] <= 0:
            raise ValueError(f"num={self.num!r}: b0 > 0 is needed for a positive static gain")

    @property
    def dc_gain(self) -> float:
        """H(0) = b0 / a0: the static rate per pps of the log stage (1 for the presets)."""
        return self.num[2] / self.den[1]

    def replace(self, **changes: object) -> TendonOrganParams:
        """A copy with ``changes`` (validated again)."""
        return dataclasses.replace(self, **changes)


def force_scales_N(params: TendonOrganParams, max_isometric_force_N: object) -> np.ndarray:
    """G2 (N) per muscle from its maximum isometric force: G2 * F_max / reference_max_force_N.

    ``max_isometric_force_N``: a scalar or an array over muscles (N, finite, > 0). Returns a
    float64 array of its shape; a G2 below :data:`MIN_FORCE_SCALE_N` is refused.
    """
    f = np.asarray(max_isometric_force_N, dtype=np.float64)
    if not np.all(np.isfinite(f) & (f > 0)):
        raise ValueError(f"max_isometric_force_N={max_isometric_force_N!r} must be finite, > 0")
    return check_force_scales(params.force_scale_N * f / params.reference_max_force_N)


def static_rate_pps(params: TendonOrganParams, force_N: object,
                    force_scale_N: object) -> np.ndarray:
    """The rate at rest at tendon force ``force_N``: dc_gain * G1 * ln(F+/G2 + 1) (pps)."""
    f = np.maximum(np.asarray(force_N, dtype=np.float64), 0.0)
    return params.dc_gain * params.gain_pps * np.log1p(f / np.asarray(force_scale_N, float))


def static_sensitivity_pps_per_N(params: TendonOrganParams, force_N: object,
                                 force_scale_N: object) -> np.ndarray:
    """d(static rate)/dF at ``force_N``: dc_gain * G1 / (G2 + F+) (pps/N)."""
    f = np.maximum(np.asarray(force_N, dtype=np.float64), 0.0)
    return params.dc_gain * params.gain_pps / (np.asarray(force_scale_N, float) + f)


CAT = TendonOrganParams(name="CAT")
"""Cat soleus, Lin & Crago (2002) as the OpenSim plugin and myogen carry it: G1 = 60 pps,
G2 = 4 N, tau = 10 ms, H(s) = (1.7 s^2 + 2.58 s + 0.4) / (s^2 + 2.2 s + 0.4). The reference
maximum force (22 N) is that of a cat soleus, an assumption (see ``docs/gto.md``): it only
matters when G2 is rescaled to another muscle."""

HUMAN = TendonOrganParams(gain_pps=40.0, name="HUMAN")
"""Human: G1 = 40 pps (myogen's human default), the cat's dynamics and G2 rule (BRA:
G2 = 4 * 987.26 / 22 = 179.5 N, TRImed: 113.5 N)."""
