"""``SpindleAfferentsVector``: the afferents of every muscle of every env of a vector env,
advanced in one batched spindle state."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from proprio_env.wrappers.capture import EnvTap, step_knots
from proprio_env.wrappers.muscles import find_muscles, model_and_data
from proprio_env.wrappers.single import (
    RATE_SCALE_PPS,
    add_afferents,
    afferent_spaces,
    bank_info,
    check_rate_scale,
)
from spindle.backends import DEFAULT_BACKEND
from spindle.chain.bank import ConstantFusimotor, SpindleBank, TemplateFusimotor
from spindle.core import SLEW_LIMIT_L0_S
from spindle.params import HUMAN, SpindleParams


class SpindleAfferentsVector(VectorWrapper):
    """:class:`~proprio_env.wrappers.SpindleAfferents` for a vector env whose sub-envs live in
    this process (``gymnasium.vector.SyncVectorEnv``: ``env.envs``).

    Every muscle of every sub-env is one spindle of one :class:`SpindleBank`, advanced by one
    batched call per 1 ms sub-step (numpy) or per env step (C). Sub-env i gives the same
    afferents as the single wrapper on that env with the same seed and actions.

    Autoreset: ``NEXT_STEP`` (Gymnasium's default: the step after a sub-env ended resets it)
    and ``SAME_STEP`` re-equilibrate that sub-env's spindles at its reset lengths; with
    ``DISABLED``, ``reset(options={"reset_mask": mask})`` does so for the masked sub-envs.
    A sub-env whose time ran backwards inside a step (it reset itself) is re-equilibrated
    too.

    ``info`` gains the single wrapper's per-muscle keys as (n_envs, M) arrays (each with its
    ``_key`` mask, all True), ``spindle_substep_source``, ``spindle_substeps_limited`` and
    ``spindle_restarts``.

    Arguments: as :class:`~proprio_env.wrappers.SpindleAfferents`.
    """

    def __init__(self, env: VectorEnv, muscles: Sequence[str] | None = None,
                 params: SpindleParams = HUMAN,
                 fusimotor: ConstantFusimotor | TemplateFusimotor | None = None,
                 observation: str = "box", rate_scale_pps: float = RATE_SCALE_PPS,
                 substep_source: str = "auto", method: str = "trapezoidal",
                 step_s: float | None = None, max_speed_L0_s: float = SLEW_LIMIT_L0_S,
                 backend: str = DEFAULT_BACKEND, lag_physics_step: bool = False) -> None:
        super().__init__(env)
        subs = getattr(env, "envs", None)
        if subs is None:
            raise ValueError(
                f"{type(env).__name__} keeps no sub-envs in this process (env.envs): the "
                "vector wrapper needs a SyncVectorEnv; with AsyncVectorEnv wrap each sub-env "
                "with SpindleAfferents in its env function instead")
        rate_scale_pps = check_rate_scale(rate_scale_pps)
        sets = [find_muscles(model_and_data(e)[0], muscles) for e in subs]
        if len({s.names for s in sets}) != 1:
            raise ValueError("the sub-envs' muscles differ: "
                             f"{sorted({s.names for s in sets})}")
        self.muscles = sets[0]
        self.taps = [EnvTap(e, s, substep_source, lag_physics_step)
                     for e, s in zip(subs, sets, strict=True)]
        if len({t.timestep_s for t in self.taps}) != 1:
            raise ValueError("the sub-envs' physics timesteps differ")
        self.rate_scale_pps = rate_scale_pps
        self.observation_mode = observation
        self.single_observation_space = afferent_spaces(env.single_observation_space,
                                                        self.muscles.n, observation)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.bank = SpindleBank(self.num_envs, self.muscles.range_low_L0,
                                self.muscles.range_high_L0, params, fusimotor, method, step_s,
                                max_speed_L0_s, backend)
        self.autoreset_mode = env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self._pending = np.zeros(self.num_envs, dtype=bool)
        self._measured = np.ones((self.num_envs, self.muscles.n))
        self._source = "frames" if all(t.recorder for t in self.taps) else "hermite"
        self._started = False

    @property
    def muscle_names(self) -> tuple[str, ...]:
        return self.muscles.names

    def reset(self, *, seed: int | list[int] | None = None,
              options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        mask = None if options is None else options.get("reset_mask")
        rows = (np.arange(self.num_envs) if mask is None
                else np.flatnonzero(np.asarray(mask, dtype=bool)))
        self._rest(rows, discard_records=True)
        self._pending[rows] = False
        self._started = True
        return self._observation(obs), self._info(info)

    def step(self, actions):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        obs, rewards, terminations, truncations, info = self.env.step(actions)
        records = [tap.records() for tap in self.taps]
        t_env = np.array([tap.time() for tap in self.taps])
        ended = np.logical_or(terminations, truncations)
        reset = self._pending.copy() if self.autoreset_mode == AutoresetMode.NEXT_STEP \
            else (ended if self.autoreset_mode == AutoresetMode.SAME_STEP
                  else np.zeros(self.num_envs, bool))
        back = ~(t_env >= self.bank.t_s)
        self.bank.restarts += int(np.count_nonzero(back & ~reset))
        reset |= back
        moving = ~reset & (t_env > self.bank.t_s)
        if moving.any():
            t, L, V, self._source = step_knots(self.taps, records, self.bank.t_s,
                                               self.bank.length_L0, self.bank.velocity_L0_s,
                                               moving)
            self.bank.advance(t, L, V, hold=~moving)
            self._measured[moving] = L[-1, moving]
        self._rest(np.flatnonzero(reset))
        self._pending = (ended if self.autoreset_mode == AutoresetMode.NEXT_STEP
                         else np.zeros(self.num_envs, bool))
        return self._observation(obs), rewards, terminations, truncations, self._info(info)

    def close(self, **kwargs: Any) -> None:
        for tap in getattr(self, "taps", ()):  # absent if __init__ refused the env
            tap.close()
        super().close(**kwargs)

    def _rest(self, rows: np.ndarray, discard_records: bool = False) -> None:
        """Rows ``rows`` at rest at their env's state now (``discard_records``: what a reset
        stepped belongs to no env step)."""
        if rows.size == 0:
            return
        now = []
        for i in rows:
            if discard_records:
                self.taps[i].records()
            now.append(self.taps[i].now())
        t = np.array([self.taps[i].rest_time(x[0]) for i, x in zip(rows, now, strict=True)])
        L = np.stack([x[1] for x in now])
        V = np.stack([x[2] for x in now])
        self.bank.reset(rows, t, L, V)
        self._measured[rows] = L

    def _observation(self, obs):
        return add_afferents(obs, self.bank.ia_pps, self.bank.ii_pps, self.observation_mode,
                             self.rate_scale_pps,
                             getattr(self.single_observation_space, "dtype", None))

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        out = dict(info)
        for key, value in bank_info(self.bank, self._measured, self._source).items():
            out[key] = value
            out[f"_{key}"] = np.ones(self.num_envs, dtype=bool)
        out["spindle_substep_source"] = self._source
        out["spindle_substeps_limited"] = self.bank.substeps_limited
        out["spindle_restarts"] = self.bank.restarts
        return out
