"""Checks of the envs' arguments: one rule per kind of value, shared by every argument.

Type confusion is refused, not coerced: a bool is not a number (``True`` is not 1 Hz), a
string is not a bool (``"no"`` would be truthy), a complex number is not real (its
imaginary part would be dropped). numpy scalars of the right kind are accepted
(``np.float32(50)``, ``np.int64(320)``, ``np.True_``). Every refusal is a ``ValueError``
naming the argument, the value and what it must be (numbers: the project's one rule,
:mod:`spindle.number_rule`, whose ``NumberError`` is a ``ValueError``).
"""

from __future__ import annotations

import numbers
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from spindle.number_rule import positive_int, real_array, real_scalar

__all__ = ["MIN_CONTROL_HZ", "check_flag", "check_instance", "check_path",
           "check_positive_int", "check_ranges_deg", "check_real", "check_real_array",
           "check_reset_options", "check_seed", "check_seeds", "check_str", "frames_per_step"]

MIN_CONTROL_HZ = 0.1
"""Slowest control rate (Hz): an env step of at most 10 s bounds the work and the buffers of
one step."""
ANGLE_OPTIONS = ("target_deg", "angle_deg")
"""The reset options that fix an episode's target and initial elbow angle (deg)."""


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


def frames_per_step(control_hz: float, timestep: float) -> int:
    """Physics steps of ``timestep`` per env step of 1/control_hz (a whole number)."""
    if not MIN_CONTROL_HZ <= control_hz <= 1.0 / timestep:
        raise ValueError(f"control_hz={control_hz!r} must lie in [{MIN_CONTROL_HZ:g}, "
                         f"{1.0 / timestep:g}] Hz (one physics step of {timestep:g} s)")
    frames = round(1.0 / (control_hz * timestep))
    if abs(frames * timestep * control_hz - 1.0) > 1e-9:
        raise ValueError(
            f"control_hz={control_hz!r}: the env step 1/control_hz must be a whole number "
            f"of physics steps of {timestep:g} s (e.g. 50, 100, 125, 250, 500 Hz)")
    return frames


def check_ranges_deg(name: str, ranges: Any, limits_deg: tuple[float, float]
                     ) -> tuple[tuple[float, float], ...]:
    """``ranges`` as a tuple of (low, high) intervals (deg) inside ``limits_deg``; the bounds
    must be real numbers (:func:`check_real`)."""
    try:
        pairs = [tuple(pair) for pair in ranges]
    except TypeError as exc:
        raise ValueError(f"{name}={ranges!r} must be a sequence of (low, high) pairs "
                         "in degrees") from exc
    if isinstance(ranges, str | bytes) or any(len(pair) != 2 for pair in pairs):
        raise ValueError(f"{name}={ranges!r} must be a sequence of (low, high) pairs "
                         "in degrees")
    out = tuple((check_real(f"{name} low", lo), check_real(f"{name} high", hi))
                for lo, hi in pairs)
    if not out:
        raise ValueError(f"{name} must hold at least one (low, high) interval")
    lo_lim, hi_lim = limits_deg
    for lo, hi in out:
        if not (lo_lim <= lo <= hi <= hi_lim):
            raise ValueError(f"{name} interval ({lo!r}, {hi!r}) must satisfy "
                             f"{lo_lim:g} <= low <= high <= {hi_lim:g} deg")
    return out


# -- reset arguments: every seed and option checked before a reset changes anything ----------
def _is_sequence(value: Any) -> bool:
    """A list, tuple, range or 1-D array (one value per sub-env)."""
    return isinstance(value, Sequence) or (isinstance(value, np.ndarray) and value.ndim == 1)


def check_seed(name: str, value: Any) -> int | None:
    """``value`` as a seed: ``None`` or an integer >= 0 (Python or numpy, not bool)."""
    if value is None:
        return None
    if _is_bool(value) or not isinstance(value, numbers.Integral) or int(value) < 0:
        raise ValueError(f"{name}={value!r} must be None or an integer >= 0 "
                         f"(got {type(value).__name__})")
    return int(value)


def check_seeds(seed: Any, n: int) -> list[int | None]:
    """The seeds of ``n`` sub-envs: ``None`` (none), an integer s (sub-env i gets s + i) or a
    sequence of ``n`` seeds (each None or an integer >= 0)."""
    if seed is None or (isinstance(seed, numbers.Integral) and not _is_bool(seed)):
        first = check_seed("seed", seed)
        return [None if first is None else first + i for i in range(n)]
    if isinstance(seed, str | bytes) or not _is_sequence(seed):
        raise ValueError(f"seed={seed!r} must be None, an integer >= 0 or a sequence of "
                         f"num_envs={n} such seeds (got {type(seed).__name__})")
    if len(seed) != n:
        raise ValueError(f"seed list has length {len(seed)}, expected num_envs={n}")
    return [check_seed(f"seed[{i}] (sub-env {i})", s) for i, s in enumerate(seed)]


def _checked_angles(name: str, value: Any, n: int | None, limits_deg: tuple[float, float]
                    ) -> np.ndarray:
    """An angle option as (n,) floats (deg) within ``limits_deg``: a real number (every env),
    or with ``n`` given a sequence of n of them (one per sub-env)."""
    lo, hi = limits_deg
    if n is not None and isinstance(value, np.ndarray) and value.shape == (n,) and (
            value.dtype.kind in "iuf"):
        x = value.astype(np.float64)
        if ((x >= lo) & (x <= hi)).all():  # the common case; NaN takes the checked path
            return x
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    if n is None or isinstance(value, str | bytes) or not _is_sequence(value):
        values, where = [value], [f"options[{name!r}]"]
    else:
        values = list(value)
        if len(values) != n:
            raise ValueError(f"options[{name!r}] holds {len(values)} values, expected one "
                             f"number or one per sub-env (num_envs={n})")
        where = [f"options[{name!r}][{i}] (sub-env {i})" for i in range(n)]
    out = np.array([check_real(w, v) for w, v in zip(where, values, strict=True)])
    for w, x in zip(where, out.tolist(), strict=True):
        if not lo <= x <= hi:
            raise ValueError(f"{w}={x!r} must lie within the joint range [{lo:g}, {hi:g}] "
                             "deg")
    return np.broadcast_to(out, (1 if n is None else n,)).copy()


def check_reset_options(options: Any, limits_deg: tuple[float, float], n: int | None = None
                        ) -> tuple[np.ndarray | None, dict[str, np.ndarray]]:
    """A reset's ``options`` checked: (reset mask or None, {option: angles (deg)}).

    ``n`` None: a single env's options, ``"target_deg"`` / ``"angle_deg"`` real numbers
    within the joint range ``limits_deg``. ``n``: a vector env's, each of those a number or
    one per sub-env (every value checked, reset or not), and ``"reset_mask"``, a (n,) bool
    array with a True. The values are (1,) or (n,) float arrays. A refusal is a ValueError
    naming the option, the sub-env and the value.
    """
    if options is None:
        return None, {}
    if not isinstance(options, Mapping):
        raise ValueError(f"options={options!r} must be a dict or None")
    known = ANGLE_OPTIONS if n is None else ("reset_mask", *ANGLE_OPTIONS)
    unknown = set(options) - set(known)
    if unknown:
        raise ValueError(f"unknown reset options {sorted(map(repr, unknown))}; known: "
                         f"{', '.join(map(repr, known))}")
    mask = options.get("reset_mask")
    if mask is not None and not (isinstance(mask, np.ndarray) and mask.dtype == bool
                                 and mask.shape == (n,) and mask.any()):
        raise ValueError(f"options['reset_mask'] must be a bool array of shape ({n},) with "
                         f"at least one True (got {mask!r})")
    return mask, {name: _checked_angles(name, options[name], n, limits_deg)
                  for name in ANGLE_OPTIONS if name in options}
