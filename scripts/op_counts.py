"""Operation counts of one spindle step, measured: what a GPU port of the step would compute.

    python scripts/op_counts.py [--spindles 512] [--steps 400]

Runs the readable implicit step (:func:`spindle.core.plain_advance`, trapezoidal, 1 ms) on
spindles driven through a physiological movement (lengths swinging over 0.8-1.2 L0 at up to
~1.5 L0/s, gamma_s 20-150 pps, gamma_d 0/100 pps, each spindle at its own phase) with every
array of the step wrapped in an ndarray subclass that counts the elements each numpy ufunc
writes. A kernel fused on a GPU (JAX under ``jit``, Warp) evaluates the same expressions per
fibre, so these are its arithmetic; the memory it must stream is the state.

Prints, per spindle per step: element operations (all ufuncs; the transcendental ones —
power, exp, log — separately), the mean Newton iterations, and the bytes of state a step
reads and writes. The last line:
``flops_per_spindle_step=<float> transcendental_per_spindle_step=<float>
state_bytes_per_spindle=<int> newton_iterations_per_step=<float>``.
"""

from __future__ import annotations

import argparse
from collections import Counter
from typing import ClassVar

import numpy as np

from spindle import core
from spindle.methods import get_method
from spindle.params import HUMAN

TRANSCENDENTAL = {"power", "float_power", "exp", "exp2", "expm1", "log", "log1p", "sqrt",
                  "cbrt", "tanh"}
"""Ufuncs that cost many arithmetic operations each (counted apart from the rest)."""
NOT_ARITHMETIC = {"isfinite", "isnan", "isinf", "greater", "less", "greater_equal",
                  "less_equal", "equal", "not_equal", "logical_and", "logical_or",
                  "logical_not", "sign", "absolute", "negative", "maximum", "minimum",
                  "clip", "copysign", "where"}
"""Comparisons, selections and sign flips: counted as operations too (a GPU executes them),
but reported apart from the floating-point arithmetic."""


class Counted(np.ndarray):
    """An ndarray whose ufuncs add the elements they write to :attr:`tally`."""

    tally: ClassVar[Counter] = Counter()

    def __array_ufunc__(self, ufunc, method, *inputs, **kwargs):
        plain = [x.view(np.ndarray) if isinstance(x, Counted) else x for x in inputs]
        if "out" in kwargs:
            kwargs["out"] = tuple(x.view(np.ndarray) if isinstance(x, Counted) else x
                                  for x in kwargs["out"])
        result = getattr(ufunc, method)(*plain, **kwargs)
        size = np.size(result[0] if isinstance(result, tuple) else result)
        Counted.tally[ufunc.__name__] += size
        if isinstance(result, np.ndarray) and result.dtype.kind == "f":
            return result.view(Counted)
        return result


def movement(n: int, steps: int, dt_s: float) -> tuple[np.ndarray, ...]:
    """(length_L0, gamma_dyn_pps, gamma_stat_pps), each (steps + 1, n): a 1.2 Hz swing of
    +-0.2 L0 about 1 L0 at each spindle's own phase, gamma_s following the length (h(x) of
    the seed paper over 0.8-1.2 L0), gamma_d 0 pps while shortening, else 100 pps."""
    t = np.arange(steps + 1)[:, None] * dt_s
    phase = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)[None, :]
    length = 1.0 + 0.2 * np.sin(2.0 * np.pi * 1.2 * t + phase)
    gamma_s = np.clip(20.0 + 130.0 * (1.2 - length) / 0.4, 20.0, 150.0)
    gamma_d = np.where(np.cos(2.0 * np.pi * 1.2 * t + phase) < 0.0, 0.0, 100.0)
    return length, gamma_d, gamma_s


def count(n: int, steps: int, dt_s: float = 1e-3) -> tuple[Counter, float]:
    """Ufunc element tallies over ``steps`` plain trapezoidal steps of ``n`` spindles, and the
    mean Newton iterations per step (the array-wide loop runs until its slowest fibre has
    converged)."""
    length, gd, gs = movement(n, steps, dt_s)
    state = core.equilibrium_state(length[0], gd[0], gs[0], HUMAN)
    c = core.columns(HUMAN)
    theta = get_method("trapezoidal").theta
    Counted.tally = Counter()
    iterations = [0]
    velocity_from_z = core._velocity_from_z

    def counting(z, c):  # one call per Newton iteration (and one per step after it)
        iterations[0] += 1
        return velocity_from_z(z, c)

    core._velocity_from_z = counting
    try:
        for k in range(1, steps + 1):
            counted = core.SpindleState(*(a.view(Counted) for a in state._arrays()))
            new = core.plain_advance(counted, length[k].view(Counted), gd[k], gs[k], dt_s,
                                     theta, c)
            core.commit(state, [np.asarray(x) for x in new], length[k], gd[k], gs[k])
    finally:
        core._velocity_from_z = velocity_from_z
    return Counted.tally, iterations[0] / steps - 1.0


def state_bytes_per_spindle() -> int:
    """Bytes of one spindle's state (what a step reads and writes)."""
    state = core.equilibrium_state(np.ones(1), np.zeros(1), np.full(1, 20.0), HUMAN)
    return int(sum(a.nbytes for a in state._arrays()))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spindles", type=int, default=512)
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args(argv)
    if args.spindles < 1 or args.steps < 1:
        parser.error("--spindles and --steps must be >= 1")
    tally, iterations = count(args.spindles, args.steps)
    per = args.spindles * args.steps
    transcendental = sum(v for k, v in tally.items() if k in TRANSCENDENTAL) / per
    logic = sum(v for k, v in tally.items() if k in NOT_ARITHMETIC) / per
    total = sum(tally.values()) / per
    arithmetic = total - transcendental - logic
    print(f"{args.spindles} spindles x {args.steps} trapezoidal steps of 1 ms, plain step; "
          f"{iterations:.2f} Newton iterations per step (until the slowest fibre converged)")
    for name, value in sorted(tally.items(), key=lambda kv: -kv[1]):
        print(f"  {name:16s} {value / per:8.1f} element ops per spindle-step")
    print(f"arithmetic {arithmetic:.0f}, transcendental {transcendental:.0f}, "
          f"comparisons/selections {logic:.0f} per spindle-step (3 fibres)")
    print(f"flops_per_spindle_step={arithmetic:.1f} "
          f"transcendental_per_spindle_step={transcendental:.1f} "
          f"state_bytes_per_spindle={state_bytes_per_spindle()} "
          f"newton_iterations_per_step={iterations:.2f}")


if __name__ == "__main__":
    main()
