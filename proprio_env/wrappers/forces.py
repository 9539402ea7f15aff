"""The wrappers' force side: each muscle's tendon force, and its Ib (Golgi tendon organs) if
asked for.

The force of a muscle is its tendon's tension from MuJoCo's ``actuator_force`` (``-gear *
force``: :meth:`~proprio_env.wrappers.muscles.MuscleSet.tension_N`), taken where the lengths
are (:mod:`proprio_env.wrappers.capture`): recorded at every physics step (the force
``mj_step`` computed at the step's start, as the lengths) and at the env's state now by
MuJoCo's ``mj_fwdActuation`` on a scratch ``MjData``; on the Hermite path only at the env
step's ends, with the straight line between them at the physics steps. With ``"ib"`` among the
wrapper's ``afferents`` the tendon organs of every muscle of every env
(:class:`~proprio_env.body.force_sense.TendonForceSense`, human preset, the force scale from the
muscle's ``gainprm[2]``) take one step per knot (the physics timestep), numpy or C.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from proprio_env.body.force_sense import TendonForceSense, max_forces_N

AFFERENTS = ("ia", "ii", "ib")
"""What a wrapper can add to the observation: spindle Ia, spindle II, tendon-organ Ib."""
DEFAULT_AFFERENTS = ("ia", "ii")


def check_afferents(afferents: Any) -> tuple[str, ...]:
    """``afferents`` as a tuple of distinct names from :data:`AFFERENTS` (at least one),
    else ValueError naming the value and the choices."""
    if isinstance(afferents, str):
        afferents = (afferents,)
    try:
        names = tuple(afferents)
    except TypeError:
        names = ()
    if not names or len(set(names)) != len(names) or any(
            not isinstance(a, str) or a not in AFFERENTS for a in names):
        raise ValueError(f"afferents={afferents!r} must be distinct names from {AFFERENTS} "
                         "(at least one)")
    return names


class ForceReadout:
    """The tendon forces of ``n`` envs x M muscles and, with ``ib``, their tendon organs.

    Args:
        model: the model; ids: the muscle actuators (M,); n: envs; ib: run the organs;
        dt_s: the organs' step (the physics timestep); backend: the organs' backend.
    """

    def __init__(self, model: mujoco.MjModel, ids: np.ndarray, n: int, ib: bool,
                 dt_s: float, backend: str) -> None:
        self.force_N = np.zeros((n, len(ids)))
        self.sense = (TendonForceSense(n, dt_s, max_forces_N(model, ids), backend)
                      if ib else None)

    def reset(self, rows: np.ndarray, force_N: np.ndarray) -> None:
        """Rows ``rows`` (k,) at rest at their forces (k, M)."""
        if self.sense is not None:
            self.sense.reset(rows, force_N)
            self.force_N[rows] = self.sense.force_N[rows]
        else:
            self.force_N[rows] = force_N

    @property
    def every_knot(self) -> bool:
        """Whether :meth:`advance` needs every knot's force (the tendon organs step through
        them), or the last knot's only (:func:`~proprio_env.wrappers.capture.step_knots`'s
        ``every_force``)."""
        return self.sense is not None

    def advance(self, force_N: np.ndarray, moving: np.ndarray) -> None:
        """Through the knots' forces (K, n, M) of the rows ``moving`` (n,) (the others held);
        without ``ib`` only the last knot's are read (K may be 1)."""
        if self.sense is not None:
            self.sense.step(force_N.transpose(1, 0, 2), hold=~moving)
            self.force_N[moving] = self.sense.force_N[moving]
        elif np.count_nonzero(moving) == moving.size:
            # (two boolean indexings: 3 us of a legs env step; count_nonzero: a third of
            # .all()'s reduction)
            self.force_N[...] = force_N[-1]
        else:
            self.force_N[moving] = force_N[-1, moving]

    @property
    def ib_pps(self) -> np.ndarray:
        """(n, M) Ib (pps); needs ``ib``."""
        return self.sense.ib_pps

    def info(self, row: int | None = None) -> dict[str, Any]:
        """``tendon_force_N`` and, with ``ib``, ``tendon_ib_pps``, ``tendon_force_held`` and
        ``tendon_force_clamped`` of row ``row`` (or every row, leading axis)."""
        pick = (lambda a: a[row].copy()) if row is not None else (lambda a: a.copy())
        out = {"tendon_force_N": pick(self.force_N)}
        if self.sense is not None:
            out["tendon_ib_pps"] = pick(self.sense.ib_pps)
            out["tendon_force_held"] = pick(self.sense.held)
            out["tendon_force_clamped"] = pick(self.sense.clamped)
        return out
