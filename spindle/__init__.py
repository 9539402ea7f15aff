"""Muscle-spindle afferents for artificial proprioception (numpy only).

The Mileusnic et al. (2006) spindle with cat and human (seed paper: G x 1/5) presets,
integrated by a theta-method (forward Euler, backward Euler, trapezoidal rule), and a stiff
reference solver (scipy, optional) to check it against.
"""

from spindle.core import (
    LENGTH_RANGE_L0,
    MAX_SPEED_L0_S,
    SpindleState,
    afferents,
    equilibrium_state,
    step,
)
from spindle.length_fits import (
    LengthFit,
    LengthFits,
    LengthFitsError,
    default_fits_path,
    load_length_fits,
)
from spindle.methods import DEFAULT_METHOD, METHODS, Method, get_method
from spindle.params import CAT, FIBRES, HUMAN, FibreParams, SpindleParams
from spindle.simulate import SpindleResult, simulate

__all__ = [
    "CAT",
    "DEFAULT_METHOD",
    "FIBRES",
    "HUMAN",
    "LENGTH_RANGE_L0",
    "MAX_SPEED_L0_S",
    "METHODS",
    "FibreParams",
    "LengthFit",
    "LengthFits",
    "LengthFitsError",
    "Method",
    "SpindleParams",
    "SpindleResult",
    "SpindleState",
    "afferents",
    "default_fits_path",
    "equilibrium_state",
    "get_method",
    "load_length_fits",
    "simulate",
    "step",
]
