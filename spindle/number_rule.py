"""The project's one rule for what counts as a number.

A number is a real number: a Python or numpy integer or float (``numbers.Real``), or a
0-d array of an integer or floating dtype. Refused, never coerced: a bool (``True`` is not
1 s), a string or bytes (``"0.001"`` is text, whatever ``float()`` makes of it), a complex
number (its imaginary part would be dropped), anything else (None, lists where one number
is expected). An array of numbers has an integer or floating dtype; bool, string, bytes,
complex and object arrays are refused, and so are lists holding any of those (numpy would
turn ``[True, 1.0]`` into ``[1.0, 1.0]``).

Two forms of the rule, one test behind both:

- arguments: :func:`real_scalar`, :func:`positive_int` and :func:`real_array` return a
  Python float / int / float64 array, or raise :class:`NumberError` naming the argument,
  the value and the limit;
- samples (the chain's pushes, where a bad sample is rejected and counted, not raised):
  :func:`sample_number` and :func:`sample_array` give NaN for every value that is not a
  real number, so the caller's rule for a non-finite sample applies.

Values pass through Python float / float64 before anything keeps them, so that a
``np.float32`` step size is the float64 number it stands for, in every cache and every
computation.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

__all__ = ["NumberError", "check_fields", "is_real_number", "positive_int", "real_array",
           "real_scalar", "sample_array", "sample_number"]

_REAL_DTYPE_KINDS = "iuf"
_NOT_NUMBERS = (bool, np.bool_, str, bytes, bytearray, complex, np.complexfloating)
_PLAIN_REALS = frozenset({float, int, np.float64, np.float32, np.float16, np.int64, np.int32,
                          np.int16, np.int8, np.uint64, np.uint32, np.uint16, np.uint8})
"""The common real types, checked by one set lookup: the chain's pushes take the rule per
sample, and ``isinstance`` against the ``numbers.Real`` ABC costs several times more."""


class NumberError(TypeError, ValueError):
    """A value that is not the number its argument needs (of the wrong kind, or outside its
    limits). Both a ``TypeError`` and a ``ValueError``, like numpy's ``AxisError``, so that
    callers catching either keep working."""


def is_real_number(value: object) -> bool:
    """Whether ``value`` is one real number of an accepted kind (it may still be non-finite
    or beyond float's range)."""
    if type(value) in _PLAIN_REALS:
        return True
    if isinstance(value, _NOT_NUMBERS):
        return False
    if isinstance(value, numbers.Real):
        return True
    return (isinstance(value, np.ndarray) and value.ndim == 0
            and value.dtype.kind in _REAL_DTYPE_KINDS)


def _kind(value: object) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of dtype {value.dtype}"
    return type(value).__name__


def real_scalar(name: str, value: object, *, low: float | None = None,
                high: float | None = None, low_open: bool = False, high_open: bool = False,
                finite: bool = True, limit_note: str = "") -> float:
    """``value`` as a Python float if it is one real number (finite unless ``finite`` is
    False) in the interval given by ``low`` / ``high`` (closed unless ``*_open``);
    :class:`NumberError` naming ``name``, the value and the limit otherwise."""
    if not is_real_number(value):
        raise NumberError(f"{name}={value!r} must be a real number (got {_kind(value)})")
    try:
        x = float(value)  # type: ignore[arg-type]
    except OverflowError as exc:  # Python ints beyond float's range
        raise NumberError(f"{name}={value!r} is too large (must be a finite real "
                          "number)") from exc
    below = low is not None and (x <= low if low_open else x < low)
    above = high is not None and (x >= high if high_open else x > high)
    if (finite and not math.isfinite(x)) or below or above:
        limit = "" if low is None and high is None else " " + _interval(
            low, high, low_open, high_open)
        raise NumberError(f"{name}={value!r} must be a "
                          f"{'finite ' if finite else ''}real number{limit}{limit_note}")
    return x


def check_fields(obj: object, names: tuple[str, ...], **limits) -> None:
    """:func:`real_scalar` (with ``limits``) on each field ``names`` of the (frozen)
    dataclass ``obj``, each stored back as the Python float it stands for."""
    for name in names:
        object.__setattr__(obj, name, real_scalar(name, getattr(obj, name), **limits))


def _interval(low, high, low_open, high_open) -> str:
    if high is None:
        return f"{'>' if low_open else '>='} {low:g}"
    if low is None:
        return f"{'<' if high_open else '<='} {high:g}"
    return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"


def positive_int(name: str, value: object, *, high: int | None = None) -> int:
    """``value`` as a Python int if it is an integer (Python or numpy, not bool) in
    ``[1, high]``; :class:`NumberError` otherwise."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral):
        raise NumberError(f"{name}={value!r} must be an integer (got {_kind(value)})")
    n = int(value)
    if n < 1 or (high is not None and n > high):
        limit = "" if high is None else f" and <= {high}"
        raise NumberError(f"{name}={value!r} must be an integer >= 1{limit}")
    return n


def _elements_are_real(items: np.ndarray) -> bool:
    # one pass over the element types, not a Python call per element
    return all((issubclass(kind, numbers.Real) and not issubclass(kind, bool | np.bool_))
               or (issubclass(kind, np.ndarray))
               for kind in {type(x) for x in items.flat})


def _as_real_array(value: object) -> np.ndarray | None:
    """``value`` as an array of an integer or floating dtype (Python ints beyond float's
    range kept as objects), or None if it holds anything else or is ragged."""
    if type(value) in (list, tuple) and {type(x) for x in value} <= _PLAIN_REALS:
        try:  # a flat list of plain numbers, the common case, without an object array
            return np.asarray(value, dtype=np.float64)
        except OverflowError:  # Python ints beyond float's range: element by element
            pass
    if isinstance(value, np.ndarray):
        if value.dtype.kind in _REAL_DTYPE_KINDS:
            return value
        if value.dtype.kind != "O":
            return None
        items = value
    else:
        if isinstance(value, _NOT_NUMBERS):
            return None
        try:
            items = np.asarray(value, dtype=object)
        except ValueError:  # ragged
            return None
    if not _elements_are_real(items):
        return None
    if any(isinstance(x, np.ndarray) for x in items.flat):  # nested arrays: look inside
        try:
            typed = np.asarray(value)
        except ValueError:
            return None
        return typed if typed.dtype.kind in _REAL_DTYPE_KINDS else None
    return items


def _shown(value: object) -> str:
    text = " ".join(repr(value).split())
    return text if len(text) <= 80 else f"{text[:60]}...{text[-12:]}"


def _first_stranger(value: object) -> str:
    """What in ``value`` is not a real number, for the error message."""
    if isinstance(value, np.ndarray):
        return f"got an array of dtype {value.dtype}"
    try:
        items = np.asarray(value, dtype=object)
    except ValueError:
        return "got a ragged nesting"
    for x in items.flat:
        if not (is_real_number(x) or isinstance(x, np.ndarray)):
            return f"it holds {x!r}, a {type(x).__name__}"
    return "got a nesting of arrays that are not all real"


def _to_float64(items: np.ndarray) -> np.ndarray:
    if items.dtype == np.float64:
        return items
    if items.dtype.kind in "iu" or (items.dtype.kind == "f" and items.dtype.itemsize <= 8):
        return items.astype(np.float64)
    with np.errstate(over="ignore"):  # float128 beyond float64 becomes inf
        try:
            return np.asarray(items, dtype=np.float64)
        except OverflowError:  # Python ints beyond float's range: inf with their sign
            return np.vectorize(_float_or_inf, otypes=[float])(items)


def _float_or_inf(x) -> float:
    try:
        return float(x)
    except OverflowError:
        return math.inf if x > 0 else -math.inf


def real_array(name: str, value: object, *, finite: bool = False) -> np.ndarray:
    """``value`` as a float64 array if it holds only real numbers (finite too with
    ``finite``); :class:`NumberError` naming ``name`` otherwise. A Python int beyond
    float's range becomes +-inf (refused with ``finite``)."""
    items = None if isinstance(value, np.ndarray) and value.dtype.kind == "O" else \
        _as_real_array(value)
    if items is None:
        raise NumberError(f"{name}={_shown(value)} must hold real numbers only "
                          f"({_first_stranger(value)})")
    x = _to_float64(items)
    if finite and not np.isfinite(x).all():
        bad = x[~np.isfinite(x)].flat[0]
        raise NumberError(f"{name} holds {bad!r}; every element must be a finite real number")
    return x


def sample_number(value: object) -> float:
    """``value`` as a float; NaN if it is not one real number (a bool, a string, complex,
    an integer beyond float's range, None...), so that the rule for a non-finite sample
    applies."""
    if type(value) is float:
        return value
    if not is_real_number(value):
        return math.nan
    try:
        return float(value)  # type: ignore[arg-type]
    except OverflowError:
        return math.nan


def sample_array(value: object) -> np.ndarray:
    """``value`` as a float64 array; NaN in place of every element that is not a real
    number (all of them if the array is of a bool, string, bytes or complex dtype; one NaN
    if it is ragged)."""
    items = _as_real_array(value)
    if items is not None and items.dtype.kind != "O":
        return _to_float64(items)
    if items is None:
        try:
            items = np.asarray(value, dtype=object)
        except ValueError:  # ragged
            return np.full(1, math.nan)
        if items.ndim == 0 or items.dtype.kind != "O":
            return np.full(items.shape, math.nan)
    return np.vectorize(sample_number, otypes=[float])(items) if items.size else \
        np.zeros(items.shape)
