"""The fixed-step theta-method family that integrates the spindle's fibre mechanics.

theta = 0 is forward Euler (the seed paper's method), theta = 1 backward Euler and
theta = 1/2 the trapezoidal rule. The step limits below were measured on the Mileusnic
Fig. 3 protocol (``scripts/spindle_accuracy.py``); the accuracy each reaches is tabulated in
``docs/spindle_accuracy.md``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Method:
    """One setting of the theta-method.

    Attributes:
        name: the name users pass (``method="trapezoidal"``).
        theta: weight of the end-of-step derivative, 0 <= theta <= 1.
        default_step_s: internal step used when ``step=None``.
        max_step_s: largest internal step accepted. For forward Euler this is a margin below
            its measured stability limit (1.417 ms on the Fig. 3 protocol); the implicit
            settings are unconditionally stable, and their limit is where
            the activation dynamics (tau >= 0.149 s) and the afferent output stop being
            represented (beyond it a step is refused rather than silently inaccurate).
    """

    name: str
    theta: float
    default_step_s: float
    max_step_s: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.theta <= 1.0:
            raise ValueError(f"theta={self.theta!r} must lie in [0, 1]")
        if not 0.0 < self.default_step_s <= self.max_step_s:
            raise ValueError(
                f"default_step_s={self.default_step_s!r} must lie in (0, max_step_s="
                f"{self.max_step_s!r}]"
            )

    @property
    def implicit(self) -> bool:
        return self.theta > 0.0


FORWARD_EULER = Method("forward_euler", 0.0, default_step_s=20e-6, max_step_s=1.2e-3)
BACKWARD_EULER = Method("backward_euler", 1.0, default_step_s=50e-6, max_step_s=10e-3)
TRAPEZOIDAL = Method("trapezoidal", 0.5, default_step_s=1e-3, max_step_s=10e-3)

METHODS: dict[str, Method] = {m.name: m for m in (FORWARD_EULER, BACKWARD_EULER, TRAPEZOIDAL)}
DEFAULT_METHOD = TRAPEZOIDAL


def get_method(method: str | Method | None) -> Method:
    """Resolve a method name (or ``None`` for the default) to a :class:`Method`."""
    if method is None:
        return DEFAULT_METHOD
    if isinstance(method, Method):
        return method
    try:
        return METHODS[method]
    except (KeyError, TypeError):
        raise ValueError(
            f"method={method!r} is not one of {sorted(METHODS)}"
        ) from None
