"""Parameters of the Mileusnic et al. (2006) muscle-spindle model.

Units: lengths in optimal fascicle lengths (L0), velocities in L0/s, forces in the model's
force units (FU), fusimotor drive and afferent rates in pulses per second (pps).

Source: Mileusnic M.P., Brown I.E., Lan N., Loeb G.E. (2006) "Mathematical models of
proprioceptors. I. Control and transduction in the muscle spindle", J Neurophysiol 96:1772-1788,
Table 1 (cat). The human preset follows the seed paper: every afferent gain G x 1/5.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from spindle.number_rule import check_fields

FIBRES = ("bag1", "bag2", "chain")
"""Intrafusal fibre order used on every fibre axis of the package."""


@dataclass(frozen=True)
class FibreParams:
    """Constants of one intrafusal fibre.

    ``beta_drive`` and ``Gamma_drive`` are the fibre's fusimotor coefficients: beta1 / Gamma1
    for bag1 (driven by gamma_dyn), beta2 / Gamma2 for bag2 and chain (driven by gamma_stat).
    ``tau_s`` is the activation time constant; 0 means the activation follows its target
    instantly (chain fibre).
    """

    KSR_FU_L0: float = 10.4649
    KPR_FU_L0: float = 0.15
    M_FU_s2_L0: float = 0.0002
    beta0_FU_s_L0: float = 0.0822
    beta_drive_FU_s_L0: float = 0.0
    Gamma_drive_FU: float = 0.0
    CL: float = 1.0
    CS: float = 0.42
    R_L0: float = 0.46
    a: float = 0.3
    LSR0_L0: float = 0.04
    LPR0_L0: float = 0.76
    LNSR_L0: float = 0.0423
    LNPR_L0: float = 0.89
    X: float = 0.7
    Lsec_L0: float = 0.04
    G_primary_pps_L0: float = 10000.0
    G_secondary_pps_L0: float = 0.0
    freq_pps: float = 60.0
    p: float = 2.0
    tau_s: float = 0.0

    def __post_init__(self) -> None:
        check_fields(self, tuple(field.name for field in dataclasses.fields(self)))
        for name in ("KSR_FU_L0", "M_FU_s2_L0", "freq_pps", "p", "a", "CL", "CS"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name}={getattr(self, name)!r} must be > 0")
        if self.tau_s < 0:
            raise ValueError(f"tau_s={self.tau_s!r} must be >= 0 (0 = instantaneous)")
        if not 0 < self.a < 1:
            raise ValueError(f"a={self.a!r} must lie in (0, 1): the damping is |v|^a")


@dataclass(frozen=True)
class SpindleParams:
    """The three fibres of one spindle and the primary-ending occlusion factor S."""

    bag1: FibreParams
    bag2: FibreParams
    chain: FibreParams
    S: float = 0.156
    name: str = "custom"

    def __post_init__(self) -> None:
        check_fields(self, ("S",), low=0.0)

    @property
    def fibres(self) -> tuple[FibreParams, FibreParams, FibreParams]:
        return (self.bag1, self.bag2, self.chain)

    def scale_gains(self, factor: float, name: str | None = None) -> SpindleParams:
        """A copy with every afferent gain (primary and secondary) multiplied by ``factor``."""
        if not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"factor={factor!r} must be finite and > 0")

        def scaled(f: FibreParams) -> FibreParams:
            return dataclasses.replace(
                f,
                G_primary_pps_L0=f.G_primary_pps_L0 * factor,
                G_secondary_pps_L0=f.G_secondary_pps_L0 * factor,
            )

        return SpindleParams(
            scaled(self.bag1), scaled(self.bag2), scaled(self.chain), self.S,
            name if name is not None else f"{self.name}*{factor:g}",
        )

    def column(self, name: str) -> np.ndarray:
        """The value of one fibre constant for (bag1, bag2, chain), shape (3, 1).

        The (3, 1) shape broadcasts against the fibre-major (3, n) working arrays of the core.
        """
        return np.array([[getattr(f, name)] for f in self.fibres], dtype=float)


CAT = SpindleParams(
    bag1=FibreParams(
        beta0_FU_s_L0=0.0605, beta_drive_FU_s_L0=0.2592, Gamma_drive_FU=0.0289,
        LNPR_L0=0.89, X=0.0, Lsec_L0=0.04,
        G_primary_pps_L0=20000.0, G_secondary_pps_L0=0.0, freq_pps=60.0, tau_s=0.149,
    ),
    bag2=FibreParams(
        beta0_FU_s_L0=0.0822, beta_drive_FU_s_L0=-0.046, Gamma_drive_FU=0.0636,
        G_primary_pps_L0=10000.0, G_secondary_pps_L0=7250.0, freq_pps=60.0, tau_s=0.205,
    ),
    chain=FibreParams(
        beta0_FU_s_L0=0.0822, beta_drive_FU_s_L0=-0.069, Gamma_drive_FU=0.0954,
        G_primary_pps_L0=10000.0, G_secondary_pps_L0=7250.0, freq_pps=90.0, tau_s=0.0,
    ),
    S=0.156,
    name="CAT",
)
"""Cat spindle, Mileusnic et al. (2006) Table 1."""

HUMAN = CAT.scale_gains(1 / 5, name="HUMAN")
"""Human spindle of the seed paper: every afferent gain G of :data:`CAT` x 1/5."""
