"""Bounded work counted, not timed: the Python and C function calls a block of code makes.

A wall-clock or CPU-time threshold in a test depends on the machine and its load; the number
of calls a push makes does not. :func:`count_calls` counts every function call (Python
functions and C functions called from Python, ctypes entry points included) made while its
block runs, and stops the block as soon as the count passes ``limit``: a call that would loop
for ever (a time gap of 1e300 s stepped 1 ms at a time) fails at once instead of hanging the
run. Work inside one C call is not seen here; the C side bounds it by construction
(``PS_CHAIN_MAX_BRIDGE_UPDATES``, ``MAX_SUBSTEPS``), and the tests check the C outputs equal
the numpy ones, whose work is counted.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np


class WorkLimitExceeded(BaseException):  # not an Exception: no "except Exception" stops it
    """Raised inside the counted block when it makes more calls than allowed."""


@dataclass
class CallCount:
    calls: int = 0


@contextmanager
def count_calls(limit: int) -> Iterator[CallCount]:
    """Count the function calls of the block; raise :class:`WorkLimitExceeded` past ``limit``."""
    count = CallCount()
    previous = sys.getprofile()

    def profile(frame, event, arg):
        if event in ("call", "c_call"):
            count.calls += 1
            if count.calls > limit:
                sys.setprofile(previous)
                raise WorkLimitExceeded(f"more than {limit} calls")

    sys.setprofile(profile)
    try:
        yield count
    finally:
        sys.setprofile(previous)


def count_each_call(obj: object, names: tuple[str, ...], limit: int) -> list[tuple[int, int]]:
    """Wrap the methods ``names`` of ``obj`` (on the instance) so that each call is counted
    with :func:`count_calls` (a wrapped method called by another is counted in the outer
    call); returns the list that receives (calls, samples) of each outer call, the samples
    being the size of its first argument (the times of a push)."""
    counts: list[tuple[int, int]] = []
    inside = []  # a counted method called by another (a block by its single pushes)

    def counted(method: Callable) -> Callable:
        def wrapper(*args, **kwargs):
            if inside:
                return method(*args, **kwargs)
            inside.append(True)
            with count_calls(limit) as n:
                try:
                    return method(*args, **kwargs)
                finally:
                    counts.append((n.calls, int(np.size(args[0])) if args else 1))
                    inside.pop()
        return wrapper

    for name in names:
        setattr(obj, name, counted(getattr(obj, name)))
    return counts
