"""The one type test of the package's settings: a real number that is not a bool."""

from __future__ import annotations


def is_real(value: object) -> bool:
    """True for an int or float (numpy scalars included), False for a bool or anything else."""
    return isinstance(value, int | float) and not isinstance(value, bool)
