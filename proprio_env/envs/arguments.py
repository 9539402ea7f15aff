"""Checks of the envs' arguments: one rule per kind of value, shared by every argument.

Type confusion is refused, not coerced: a bool is not a number (``True`` is not 1 Hz), a
string is not a bool (``"no"`` would be truthy), a complex number is not real (its
imaginary part would be dropped). numpy scalars of the right kind are accepted
(``np.float32(50)``, ``np.int64(320)``, ``np.True_``). Every refusal is a ``ValueError``
naming the argument, the value and what it must be (numbers: the project's one rule,
:mod:`spindle.number_rule`, whose ``NumberError`` is a ``ValueError``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from spindle.number_rule import positive_int, real_array, real_scalar

__all__ = ["check_flag", "check_instance", "check_path", "check_positive_int",
           "check_real", "check_real_array", "check_str"]


def _is_bool(value: Any) -> bool:
    return isinstance(value, bool | np.bool_)


def check_real(name: str, value: Any, *, low: float | None = None,
               low_open: bool = False) -> float:
    """``value`` as a finite float: a real number (Python or numpy, not bool) ``>= low``
    (``> low`` with ``low_open``); the project's rule, :func:`spindle.number_rule.real_scalar`."""
    return real_scalar(name, value, low=low, low_open=low_open)


def check_positive_int(name: str, value: Any, *, high: int | None = None) -> int:
    """``value`` as an int: an integer (Python or numpy, not bool) in ``[1, high]``."""
    return positive_int(name, value, high=high)


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
    """``value`` as a new float64 array if its elements are real numbers
    (:func:`spindle.number_rule.real_array`: complex, bool, string, bytes and object arrays
    are refused; a Python int beyond float's range becomes inf)."""
    return np.array(real_array(name, value), dtype=np.float64)  # a copy: callers keep it
