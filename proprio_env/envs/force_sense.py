"""The force sense of ``n`` envs: BRA and TRImed tendon forces in, Ib (Golgi tendon organs) out.

The envs' ``include_ib`` (on in the ``-v1`` ids) adds the Ib rate of each muscle's tendon
organs (Lin & Crago 2002, :mod:`spindle.tendon_organ`, human preset) to the observation. The
tendon force of each muscle is read after every physics step (what the drive's
``tendon_forces_N`` makes of MuJoCo's ``actuator_force``) and the ``2 n`` organs are
advanced through all of them in one call (``make_tendon_organs(...).run``, numpy or C): the
organs' step is the physics step, exact for a force linear between steps, and the organs end
every env step at the physics' time.

The force scale of each muscle is the project's rule (:func:`force_scales_N`) on the model's
own maximum isometric force (``actuator_gainprm[:, 2]``; Arm26's 987.26 N and 624.3 N in
``elbow.xml``).

Handling rule (counted, never a NaN): a non-finite tendon force (only possible where the
physics diverged: in an env that is about to raise or be reset) holds the muscle's previous
force, counted in :attr:`TendonForceSense.held`; a force above
``spindle.tendon_organ.MAX_FORCE_N`` (10^5 N, 60x the strongest force the elbow's muscles or
servo can exert) is clamped to it, counted in :attr:`TendonForceSense.clamped`. A negative
force (a slack tendon) is taken as 0 by the organs (their rule).
"""

from __future__ import annotations

import numpy as np

from spindle.tendon_organ import MAX_FORCE_N, make_tendon_organs
from spindle.tendon_organ_params import HUMAN, TendonOrganParams, force_scales_N


class TendonForceSense:
    """The tendon organs of ``n`` envs x 2 muscles (organ ``2 i + j``: env i, muscle j).

    Args:
        n: envs; dt_s: the physics step (s), one organ step per physics step;
        max_force_N: (2,) the muscles' maximum isometric force (N), for the force scale;
        backend: resolved backend name (``"numpy"`` or ``"c"``); params: the preset.

    ``force_N`` and ``ib_pps`` (n, 2) are the latest tendon forces (N, as the organs took
    them) and rates (pps); ``held`` and ``clamped`` (n,) count the handling rule's cases
    since construction.
    """

    def __init__(self, n: int, dt_s: float, max_force_N: np.ndarray, backend: str,
                 params: TendonOrganParams = HUMAN) -> None:
        self.n = n
        self.force_scale_N = force_scales_N(params, max_force_N)
        self.organs = make_tendon_organs(np.tile(self.force_scale_N, n), params, dt_s,
                                         backend=backend)
        self.force_N = np.zeros((n, 2))
        self.ib_pps = self.organs.rate_pps().reshape(n, 2)
        self.held = np.zeros(n, dtype=np.int64)
        self.clamped = np.zeros(n, dtype=np.int64)

    @property
    def backend(self) -> str:
        return self.organs.backend

    def checked(self, force_N: np.ndarray, previous_N: np.ndarray) -> np.ndarray:
        """``force_N`` (m, F, 2) after the handling rule, frame by frame from
        ``previous_N`` (m, 2); the counts are not changed (see :meth:`count`)."""
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
        """Add the handling rule's cases of ``force_N`` (m, F, 2) to the counts of
        ``envs`` (None: every env)."""
        rows = slice(None) if envs is None else envs
        self.held[rows] += np.count_nonzero(~np.isfinite(force_N), axis=(1, 2))
        self.clamped[rows] += np.count_nonzero(np.isfinite(force_N) & (force_N > MAX_FORCE_N),
                                               axis=(1, 2))

    def step(self, force_N: np.ndarray) -> np.ndarray:
        """Advance every organ through the tendon forces ``force_N`` (n, F, 2) after each of
        the env step's F physics steps; returns Ib (n, 2) at the step's end."""
        f = self.checked(force_N, self.force_N)
        frames = f.shape[1]
        rates = self.organs.run(f.transpose(1, 0, 2).reshape(frames, 2 * self.n))
        self.count(force_N)
        self.force_N[:] = f[:, -1]
        self.ib_pps = rates[-1].reshape(self.n, 2)
        return self.ib_pps

    def reset(self, envs: np.ndarray, force_N: np.ndarray) -> None:
        """The organs of ``envs`` (m,) at rest at their tendon forces ``force_N`` (m, 2)."""
        f = self.checked(force_N[:, None, :], np.zeros_like(force_N))[:, 0]
        rows = (2 * np.asarray(envs)[:, None] + np.arange(2)).ravel()
        rates = self.organs.reset(f.ravel(), rows)
        self.count(force_N[:, None, :], envs)
        self.force_N[envs] = f
        self.ib_pps = rates.reshape(self.n, 2)
