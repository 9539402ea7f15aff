"""Checks of the envs' arguments: one rule per kind of value, shared by every argument.

Type confusion is refused, not coerced: a bool is not a number (``True`` is not 1 Hz), a
string is not a bool (``"no"`` would be truthy), a complex number is not real (its
imaginary part would be dropped). numpy scalars of the right kind are accepted
(``np.float32(50)``, ``np.int64(320)``, ``np.True_``). Every refusal is a ``ValueError``
naming the argument, the value and what it must be.
"""

from __future__ import annotations

import math
import numbers
import os
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["check_flag", "check_instance", "check_path", "check_positive_int",
           "check_real", "check_real_array", "check_str"]


def _is_bool(value: Any) -> bool:
    return isinstance(value, bool | np.bool_)


def check_real(name: str, value: Any, *, low: float | None = None,
               low_open: bool = False) -> float:
    """``value`` as a finite float: a real number (Python or numpy, not bool) ``>= low``
    (``> low`` with ``low_open``)."""
    if _is_bool(value) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name}={value!r} must be a real number (got {type(value).__name__})")
    try:
        x = float(value)
    except OverflowError as exc:  # Python ints beyond the float range
        raise ValueError(f"{name}={value!r} is too large (must be finite)") from exc
    if not math.isfinite(x):
        raise ValueError(f"{name}={value!r} must be finite")
    if low is not None and (x <= low if low_open else x < low):
        raise ValueError(f"{name}={value!r} must be {'>' if low_open else '>='} {low:g}")
    return x


def check_positive_int(name: str, value: Any, *, high: int | None = None) -> int:
    """``value`` as an int: an integer (Python or numpy, not bool) in ``[1, high]``."""
    if _is_bool(value) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name}={value!r} must be an integer (got {type(value).__name__})")
    n = int(value)
    if n < 1 or (high is not None and n > high):
        limit = "" if high is None else f" and <= {high}"
        raise ValueError(f"{name}={value!r} must be >= 1{limit}")
    return n


def check_flag(name: str, value: Any) -> bool:
    """``value`` as a bool: only ``True``/``False`` (or numpy's)."""
    if not _is_bool(value):
        raise ValueError(f"{name}={value!r} must be True or False "
                         f"(got {type(value).__name__})")
    return bool(value)


def check_str(name: str, value: Any, choices: tuple[str, ...] | None = None) -> str:
    """``value`` as a str, one of ``choices`` if given."""
    if not isinstance(value, str):
        raise ValueError(f"{name}={value!r} must be a string (got {type(value).__name__})")
    if choices is not None and value not in choices:
        raise ValueError(f"{name}={value!r} is not one of {choices}")
    return str(value)


def check_path(name: str, value: Any) -> Path:
    """``value`` as a Path: a str or an ``os.PathLike``."""
    if not isinstance(value, str | os.PathLike):
        raise ValueError(f"{name}={value!r} must be a file path (got {type(value).__name__})")
    return Path(value)


def check_instance(name: str, value: Any, cls: type) -> Any:
    """``value`` itself if it is a ``cls``."""
    if not isinstance(value, cls):
        raise ValueError(f"{name}={value!r} must be a {cls.__name__} "
                         f"(got {type(value).__name__})")
    return value


def check_real_array(name: str, value: Any) -> np.ndarray:
    """``value`` as a float64 array if its elements are real numbers: integer or floating
    dtype. Complex (the imaginary part would be dropped), bool, string and object arrays
    (e.g. Python ints beyond the float range) are refused."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nesting
        raise ValueError(f"{name} {value!r} is not a numeric array") from exc
    if a.dtype.kind not in "iuf":
        raise ValueError(f"{name} {value!r} must hold real numbers (got dtype {a.dtype})")
    with np.errstate(over="ignore"):  # float128 beyond float64 becomes inf, refused as such
        return a.astype(np.float64)
