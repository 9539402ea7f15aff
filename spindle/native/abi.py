"""The C interface as Python sees it: ``proprio.h``'s status codes and ctypes struct mirrors.

One mirror of the header for every binding (:mod:`spindle.native.spindle`,
:mod:`spindle.native.chain`, :mod:`spindle.native.fixed`, the Cortex-M0+ bench in
:mod:`spindle.native.m0plus`): :class:`Status` (``enum ps_status``), ``ps_real`` per build
variant, and the spindle section's structs (``ps_params``, ``ps_spindle``, ``ps_plan``,
``ps_plan_fx``, ``ps_spindle_fx``). The chain section's structs live beside their only user,
:mod:`spindle.native.chain`. :func:`header_status_codes` and :func:`header_constants` read
the header itself, so the tests compare these mirrors with it rather than trust them.
"""

from __future__ import annotations

import ctypes
import enum
import re
from functools import cache
from pathlib import Path

import numpy as np

from spindle.native.build import HEADER, VARIANTS
from spindle.params import SpindleParams


class Status(enum.IntEnum):
    """``enum ps_status`` of ``proprio.h`` (names and values checked against the header)."""

    PS_OK = 0
    PS_ERR_NULL = 1
    PS_ERR_NONFINITE = 2
    PS_ERR_LENGTH_RANGE = 3
    PS_ERR_NEGATIVE_DRIVE = 4
    PS_ERR_STEP = 5
    PS_ERR_SPEED = 6
    PS_ERR_NO_CONVERGENCE = 7
    PS_ERR_METHOD = 8
    PS_ERR_CONFIG = 9
    PS_ERR_ANGLE_RANGE = 10
    PS_ERR_NOT_RESET = 11
    PS_ERR_INTERVAL = 12
    PS_ERR_ARGUMENT = 13
    PS_ERR_FORCE_RANGE = 14
    PS_ERR_BUFFER_FULL = 15
    PS_ERR_CHARGE = 16


INT32_MAX = 2**31 - 1


def checked_int32(values: object, name: str) -> np.ndarray:
    """``values`` (already scaled to a fixed-point format and rounded) as int64, or ValueError
    naming ``name``, the first value out of range and the limit: ctypes passes an int32
    argument modulo 2^32 without a word, so a value beyond it became another, valid-looking
    one (a length of 256.5 L0 in Q24 arrived as 0.5 L0)."""
    v = np.asarray(values)
    bad = ~(np.abs(v.astype(np.float64)) <= INT32_MAX)  # NaN fails too
    if np.any(bad):
        raise ValueError(f"{name}={v[bad].flat[0]!r} (in its fixed-point format) does not fit "
                         f"an int32 (|value| <= {INT32_MAX})")
    return v.astype(np.int64)


def status_name(code: int) -> str:
    """The header's name of a status code (``"unknown status <code>"`` for any other int)."""
    try:
        return Status(code).name
    except ValueError:
        return f"unknown status {code}"


def header_status_codes(header: Path = HEADER) -> dict[str, int]:
    """``enum ps_status`` as written in ``header``: name -> value."""
    text = _without_comments(header.read_text())
    body = re.search(r"enum\s+ps_status\s*\{(.*?)\}", text, re.S)
    if body is None:
        raise ValueError(f"{header} declares no enum ps_status")
    pairs = re.findall(r"(\w+)\s*=\s*(\d+)", body.group(1))
    return {name: int(value) for name, value in pairs}


def header_constants(header: Path = HEADER) -> dict[str, float]:
    """Every ``#define NAME <number>`` of ``header`` (integers as int, a trailing L dropped)."""
    out: dict[str, float] = {}
    for name, value in re.findall(r"^#define\s+(\w+)\s+([-+0-9.eE]+)L?\b",
                                  _without_comments(header.read_text()), re.M):
        out[name] = int(value) if re.fullmatch(r"[-+]?\d+", value) else float(value)
    return out


def _without_comments(text: str) -> str:
    return re.sub(r"/\*.*?\*/", " ", text, flags=re.S)


def real_type(variant: str = "double") -> type:
    """The ctypes type of ``ps_real`` in ``variant``."""
    return ctypes.c_float if variant == "float" else ctypes.c_double


def _check_variant(variant: str) -> None:
    if variant not in VARIANTS:
        raise ValueError(f"variant={variant!r} is not one of {VARIANTS}")


def structs(variant: str = "double") -> tuple[type, type]:
    """ctypes mirrors of (``ps_params``, ``ps_spindle``) for ``variant``.

    One pair of classes per variant however it is called (``structs()`` and
    ``structs("double")`` must agree, or ctypes refuses one's pointers where the other's are
    declared).
    """
    _check_variant(variant)
    return _structs(variant)


@cache
def _structs(variant: str) -> tuple[type, type]:
    real = real_type(variant)
    fibre = real * 3

    class PsParams(ctypes.Structure):
        _fields_ = [(name, fibre) for name in PARAMS_FIELDS] + [("S", real)]

    class PsSpindle(ctypes.Structure):
        _fields_ = [("T", fibre), ("v", fibre), ("z", fibre), ("f", fibre),
                    ("L", real), ("gd", real), ("gs", real)]

    return PsParams, PsSpindle


# ps_params field -> spindle.FibreParams attribute, in the header's order.
PARAMS_FIELDS = {
    "KSR": "KSR_FU_L0", "KPR": "KPR_FU_L0", "M": "M_FU_s2_L0",
    "beta0": "beta0_FU_s_L0", "beta_drive": "beta_drive_FU_s_L0",
    "Gamma_drive": "Gamma_drive_FU", "CL": "CL", "CS": "CS", "R": "R_L0", "a": "a",
    "LSR0": "LSR0_L0", "LPR0": "LPR0_L0", "LNSR": "LNSR_L0", "LNPR": "LNPR_L0", "X": "X",
    "Lsec": "Lsec_L0", "G_pri": "G_primary_pps_L0", "G_sec": "G_secondary_pps_L0",
    "freq": "freq_pps", "p": "p", "tau": "tau_s",
}


def params_struct(params: SpindleParams, variant: str = "double") -> ctypes.Structure:
    """``params`` as a filled ``ps_params``."""
    PsParams, _ = structs(variant)
    out = PsParams()
    for field, attr in PARAMS_FIELDS.items():
        getattr(out, field)[:] = [getattr(f, attr) for f in params.fibres]
    out.S = params.S
    return out


# ps_plan of proprio.h, field by field in the header's order.
PLAN_SCALARS = ("h", "theta", "one_minus_theta", "th_h", "max_dL", "S")
PLAN_FLAGS = ("p_is_2", "a_is_03", "explicit_step", "uses_F0")
PLAN_FIBRE_FIELDS = (
    ("KSR", "inv_KSR", "c_f0", "c_a0", "c_a1", "c_a01"),
    ("freq_p", "p", "a", "beta0", "beta_drive", "Gamma_drive", "CL", "CS", "KPR", "LPR0", "R",
     "LSR0", "LSR0_R", "LSR0_LPR0", "h_KSR", "h_M", "c_Av", "a2", "inv_a2", "M_h", "th_h_KSR",
     "th_k1", "th_KPR", "th_CS", "th_dC", "stretch0", "G_pri", "c_sec1", "c_sec2", "sec_off"),
)


def plan_struct(variant: str = "double") -> type:
    """ctypes mirror of ``ps_plan`` (the embedded fast path's precomputed constants)."""
    _check_variant(variant)
    return _plan_struct(variant)


@cache
def _plan_struct(variant: str) -> type:
    real = real_type(variant)

    class PsPlan(ctypes.Structure):
        _fields_ = ([(name, real) for name in PLAN_SCALARS]
                    + [(name, ctypes.c_int) for name in PLAN_FLAGS]
                    + [(name, real * 3) for name in PLAN_FIBRE_FIELDS[0]]
                    + [("lagged", ctypes.c_int * 3)]
                    + [(name, real * 3) for name in PLAN_FIBRE_FIELDS[1]])

    return PsPlan


# ps_plan_fx and ps_spindle_fx of proprio.h (the fixed-point step), field by field.
FX_ROOT_TABLE = 31
"""``PS_FX_ROOT_TABLE``: entries of ``ps_plan_fx.root10``."""
PLAN_FX_SCALARS = ("max_dL", "one_minus_theta", "th_h", "om_h", "S", "tol", "y_max", "v_max",
                   "dg_shift")
PLAN_FX_FIBRE_FIELDS = (
    "KSR", "inv_KSR", "inv_k1", "thKSR", "c_f0", "c_fa", "freq", "Gamma_drive", "KPR",
    "LSR0_R", "LSR0_LPR0", "cv", "c_Av", "th_h_KSR", "a2", "inv_a2", "r_cap", "thCL_b0",
    "thCL_bd", "thCS_b0", "thCS_bd", "omCL_b0", "omCL_bd", "omCS_b0", "omCS_bd", "G_T", "G_0",
    "cs_T", "c_sec2", "s_0")


@cache
def fixed_structs() -> tuple[type, type]:
    """ctypes mirrors of (``ps_plan_fx``, ``ps_spindle_fx``): all int32, one layout for both
    variants (the fixed-point step has no ``ps_real``)."""
    i32 = ctypes.c_int32

    class PsPlanFxFibre(ctypes.Structure):
        _fields_ = [(name, i32) for name in PLAN_FX_FIBRE_FIELDS]

    class PsPlanFx(ctypes.Structure):
        _fields_ = ([(name, i32) for name in PLAN_FX_SCALARS]
                    + [("fibre", PsPlanFxFibre * 3), ("root10", i32 * FX_ROOT_TABLE)])

    class PsSpindleFx(ctypes.Structure):
        _fields_ = ([(name, i32 * 3) for name in ("T", "v", "z", "f", "target")]
                    + [(name, i32) for name in ("L", "gd", "gs")])

    return PsPlanFx, PsSpindleFx
