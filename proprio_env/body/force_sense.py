"""The force sense of ``n`` envs of ``M`` muscles: tendon forces in, Ib (Golgi tendon organs) out.

Used by the elbow envs (``include_ib``, on in the ``-v1`` ids: BRA and TRImed) and the
any-model wrappers (``afferents=(..., "ib")``). The Ib rate of each muscle's tendon organs
(Lin & Crago 2002, :mod:`spindle.tendon_organ`, human preset) follows the tendon force read
after every physics step; the ``n M`` organs are advanced through all of an env step's
samples in one call (``make_tendon_organs(...).run``, numpy or C): the organs' step is the
physics step, exact for a force linear between steps, so the organs end every env step at
the physics' time.

The force scale of each muscle is the project's rule (:func:`force_scales_N`) on the model's
own maximum isometric force (MuJoCo's ``actuator_gainprm[:, 2]``, :func:`max_forces_N`;
Arm26's 987.26 N and 624.3 N in ``elbow.xml``).

Handling rule (counted, never a NaN): a non-finite tendon force (only possible where the
physics diverged: in an env that is about to raise or be reset) holds the muscle's previous
force, counted in :attr:`TendonForceSense.held`; a force above
``spindle.tendon_organ.MAX_FORCE_N`` (10^5 N, 60x the strongest force the elbow's muscles or
servo can exert, 10x any human tendon's) is clamped to it, counted in
:attr:`TendonForceSense.clamped`. A negative force (a slack tendon, or a muscle model that
pushes) is taken as 0 by the organs (their rule).
"""

from __future__ import annotations

import mujoco
import numpy as np

from spindle.tendon_organ import MAX_FORCE_N, make_tendon_organs
from spindle.tendon_organ_params import HUMAN, TendonOrganParams, force_scales_N


def max_forces_N(model: mujoco.MjModel, actuator_ids: np.ndarray) -> np.ndarray:
    """The maximum isometric force (N) of MuJoCo muscle actuators: ``actuator_gainprm[:, 2]``
    (``force=`` in MJCF; MuJoCo's compiler fills it in from ``scale`` when it is left at
    -1); ValueError naming the actuator unless it is finite and > 0."""
    ids = np.asarray(actuator_ids, dtype=int)
    f = np.array(model.actuator_gainprm[ids, 2], dtype=np.float64)
    bad = ~(np.isfinite(f) & (f > 0))
    if bad.any():
        i = int(ids[np.argmax(bad)])
        raise ValueError(f"actuator {model.actuator(i).name!r} has a maximum isometric force "
                         f"(gainprm[2]) of {f[np.argmax(bad)]!r}: the tendon organs need one "
                         "finite and > 0 (N)")
    return f


class TendonForceSense:
    """The tendon organs of ``n`` envs x ``M`` muscles (organ ``M i + j``: env i, muscle j).

    Args:
        n: envs; dt_s: the physics step (s), one organ step per physics step;
        max_force_N: (M,) the muscles' maximum isometric force (N), for the force scale;
        backend: ``"numpy"``, ``"c"`` or ``"auto"``; params: the preset.

    ``force_N`` and ``ib_pps`` (n, M) are the latest tendon forces (N, as the organs took
    them) and rates (pps); ``held`` and ``clamped`` (n,) count the handling rule's cases
    since construction.
    """

    def __init__(self, n: int, dt_s: float, max_force_N: np.ndarray, backend: str,
                 params: TendonOrganParams = HUMAN) -> None:
        self.n = n
        self.force_scale_N = force_scales_N(params, max_force_N)
        self.m = m = self.force_scale_N.shape[0]
        self.organs = make_tendon_organs(np.tile(self.force_scale_N, n), params, dt_s,
                                         backend=backend)
        self.force_N = np.zeros((n, m))
        self.ib_pps = self.organs.rate_pps().reshape(n, m)
        self.held = np.zeros(n, dtype=np.int64)
        self.clamped = np.zeros(n, dtype=np.int64)
        self.last_forces_N = np.zeros((n, 0, m))
        self.steps = self.resets = 0  # calls, so that a checker knows what happened

    @property
    def backend(self) -> str:
        return self.organs.backend

    def checked(self, force_N: np.ndarray, previous_N: np.ndarray) -> np.ndarray:
        """``force_N`` (k, F, M) after the handling rule, frame by frame from
        ``previous_N`` (k, M); the counts are not changed (see :meth:`count`)."""
        out = np.array(force_N, dtype=np.float64)
        last = previous_N
        for k in range(out.shape[1]):
            frame = out[:, k]
            bad = ~np.isfinite(frame)
            if bad.any():
                frame[bad] = last[bad]
            np.minimum(frame, MAX_FORCE_N, out=frame)
            last = frame
        return out

    def count(self, force_N: np.ndarray, envs: np.ndarray | None = None) -> None:
        """Add the handling rule's cases of ``force_N`` (k, F, M) to the counts of
        ``envs`` (None: every env)."""
        rows = slice(None) if envs is None else envs
        self.held[rows] += np.count_nonzero(~np.isfinite(force_N), axis=(1, 2))
        self.clamped[rows] += np.count_nonzero(np.isfinite(force_N) & (force_N > MAX_FORCE_N),
                                               axis=(1, 2))

    def _ruled(self, force_N: np.ndarray, previous_N: np.ndarray,
               envs: np.ndarray | None = None) -> np.ndarray:
        """``force_N`` under the handling rule, its cases counted (one reduction when every
        force is finite and in range, the common case: NaN and inf fail the comparison)."""
        if float(np.max(force_N, initial=0.0)) <= MAX_FORCE_N:
            return np.asarray(force_N, dtype=np.float64)
        self.count(force_N, envs)
        return self.checked(force_N, previous_N)

    def step(self, force_N: np.ndarray, hold: np.ndarray | None = None) -> np.ndarray:
        """Advance every organ through the tendon forces ``force_N`` (n, F, M) after each of
        the env step's F physics steps; returns Ib (n, M) at the step's end. The envs with
        ``hold`` (n,) True are left as they were (their forces are not read)."""
        n, m = self.n, self.m
        held = None if hold is None or not np.any(hold) else np.flatnonzero(hold)
        if held is not None:
            force_N = np.array(force_N, dtype=np.float64)
            force_N[held] = self.force_N[held, None, :]
            saved = self.organs.rows_state(self._rows(held))
        f = self._ruled(force_N, self.force_N)
        frames = f.shape[1]
        rates = self.organs.run(f.transpose(1, 0, 2).reshape(frames, m * n))[-1]
        if held is not None:
            rates = self.organs.set_rows_state(self._rows(held), saved)
        self.force_N[:] = f[:, -1]
        self.last_forces_N = f  # what the organs took, (n, F, M): for twins and checks
        self.steps += 1
        self.ib_pps = rates.reshape(n, m)
        return self.ib_pps

    def _rows(self, envs: np.ndarray) -> np.ndarray:
        return (self.m * np.asarray(envs)[:, None] + np.arange(self.m)).ravel()

    def reset(self, envs: np.ndarray, force_N: np.ndarray) -> None:
        """The organs of ``envs`` (k,) at rest at their tendon forces ``force_N`` (k, M)."""
        f = self._ruled(force_N[:, None, :], np.zeros_like(force_N), envs)[:, 0]
        rates = self.organs.reset(f.ravel(), self._rows(envs))
        self.resets += 1
        self.force_N[envs] = f
        self.ib_pps = rates.reshape(self.n, self.m)
