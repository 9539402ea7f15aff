"""``SpindleAfferentsVector``: the afferents of every muscle of every env of a vector env,
advanced in one batched spindle state."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv, VectorWrapper
from gymnasium.vector.utils import batch_space

from proprio_env.wrappers.capture import MAX_INTERVAL_S, EnvTap, check_max_interval, step_knots
from proprio_env.wrappers.forces import DEFAULT_AFFERENTS, ForceReadout, check_afferents
from proprio_env.wrappers.muscles import find_muscles, model_and_data
from proprio_env.wrappers.single import (
    RATE_SCALE_PPS,
    add_afferents,
    afferent_rates,
    afferent_spaces,
    bank_info,
    check_rate_scale,
)
from spindle.backends import DEFAULT_BACKEND
from spindle.chain.driver import ConstantFusimotor, SpindleDriver, TemplateFusimotor
from spindle.core import SLEW_LIMIT_L0_S
from spindle.params import HUMAN, SpindleParams


class SpindleAfferentsVector(VectorWrapper):
    """:class:`~proprio_env.wrappers.SpindleAfferents` for a vector env whose sub-envs live in
    this process (``gymnasium.vector.SyncVectorEnv``: ``env.envs``).

    Every muscle of every sub-env is one spindle of one :class:`SpindleDriver`, advanced by one
    batched call per 1 ms sub-step (numpy) or per env step (C). Sub-env i gives the same
    afferents as the single wrapper on that env with the same seed and actions.

    Autoreset: ``NEXT_STEP`` (Gymnasium's default: the step after a sub-env ended resets it)
    and ``SAME_STEP`` re-equilibrate that sub-env's spindles at its reset lengths; with
    ``DISABLED``, ``reset(options={"reset_mask": mask})`` does so for the masked sub-envs.
    With ``SAME_STEP`` the ending step's afferents are computed too (the wrapper keeps each
    sub-env's state when the vector env resets it, through an instance attribute ``reset``
    on the sub-env): ``info["final_obs"][i]`` is the wrapped observation (in
    :attr:`single_observation_space`) and ``info["final_info"][i]`` holds that step's
    ``spindle_*`` keys. A sub-env whose time ran backwards inside a step (it reset itself),
    jumped by more than ``max_interval_s``, or moved by another time than the others' is
    re-equilibrated at its state (counted in ``spindle_restarts``).

    ``info`` gains the single wrapper's per-muscle keys as (n_envs, M) arrays (each with its
    ``_key`` mask, all True; the tendon forces and, with ``"ib"``, Ib and the force rule's
    counts too), ``spindle_substep_source``, ``spindle_substeps_limited`` and
    ``spindle_restarts``.

    Arguments: as :class:`~proprio_env.wrappers.SpindleAfferents`.
    """

    def __init__(self, env: VectorEnv, muscles: Sequence[str] | None = None,
                 params: SpindleParams = HUMAN,
                 fusimotor: ConstantFusimotor | TemplateFusimotor | None = None,
                 observation: str = "box", rate_scale_pps: float = RATE_SCALE_PPS,
                 substep_source: str = "auto", method: str = "trapezoidal",
                 step_s: float | None = None, max_speed_L0_s: float = SLEW_LIMIT_L0_S,
                 backend: str = DEFAULT_BACKEND, lag_physics_step: bool = False,
                 max_interval_s: float = MAX_INTERVAL_S,
                 afferents: Sequence[str] = DEFAULT_AFFERENTS) -> None:
        super().__init__(env)
        afferents = check_afferents(afferents)
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
        timesteps = {float(model_and_data(e)[0].opt.timestep) for e in subs}
        if len(timesteps) != 1:
            raise ValueError(f"the sub-envs' physics timesteps differ: {sorted(timesteps)}")
        bank = SpindleDriver(len(subs), self.muscles.range_low_L0, self.muscles.range_high_L0,
                           params, fusimotor, method, step_s, max_speed_L0_s, backend)
        timestep_s = timesteps.pop()
        self.max_interval_s = max(check_max_interval(
            max_interval_s, timestep_s, bank.step_s, getattr(e.unwrapped, "dt", None))
            for e in subs)
        dts = {getattr(e.unwrapped, "dt", None) for e in subs}
        dt = dts.pop() if len(dts) == 1 else None
        self._env_steps = (round(dt / timestep_s) if isinstance(dt, float | int) and dt > 0
                           else None)  # physics steps per env step, if the envs say
        self.autoreset_mode = env.metadata.get("autoreset_mode", AutoresetMode.NEXT_STEP)
        self.rate_scale_pps = rate_scale_pps
        self.observation_mode = observation
        self.afferents = afferents
        self.single_observation_space = afferent_spaces(env.single_observation_space,
                                                        self.muscles.n, observation, afferents)
        self.forces = ForceReadout(model_and_data(subs[0])[0], self.muscles.ids, len(subs),
                                   "ib" in afferents, timestep_s, bank.backend)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        # the sub-envs are hooked last, once every argument has been accepted
        self.taps = [EnvTap(e, s, substep_source, lag_physics_step, self.max_interval_s)
                     for e, s in zip(subs, sets, strict=True)]
        self._final_hooks = ([FinalStateOnReset(e, tap) for e, tap in
                              zip(subs, self.taps, strict=True)]
                             if self.autoreset_mode == AutoresetMode.SAME_STEP else [])
        self.bank = bank
        self._pending = np.zeros(self.num_envs, dtype=bool)
        self._measured = np.ones((self.num_envs, self.muscles.n))
        self._source = "frames" if all(t.recorder is not None for t in self.taps) \
            else "hermite"
        self._started = False

    @property
    def muscle_names(self) -> tuple[str, ...]:
        return self.muscles.names

    @property
    def substep_source(self) -> str:
        """``"frames"`` or ``"hermite"``: how the lengths inside the last step were obtained
        (see :attr:`SpindleAfferents.substep_source`)."""
        return self._source

    def reset(self, *, seed: int | list[int] | None = None,
              options: dict[str, Any] | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        mask = None if options is None else options.get("reset_mask")
        rows = (np.arange(self.num_envs) if mask is None
                else np.flatnonzero(np.asarray(mask, dtype=bool)))
        self._rest(rows, discard_records=True)
        self._pending[rows] = False
        self._source = "frames" if all(t.recorder is not None for t in self.taps) \
            else "hermite"
        self._started = True
        return self._observation(obs), self._info(info)

    def step(self, actions):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        for hook in self._final_hooks:
            hook.armed = True
        try:
            obs, rewards, terminations, truncations, info = self.env.step(actions)
        except BaseException:
            # the vector env stepped some sub-envs and refused another: those it reset
            # rest at their reset state, as the rest of this step is lost anyway
            frozen = np.flatnonzero([tap.final is not None for tap in self.taps])
            for i in frozen:
                self.taps[i].thaw()
            self._rest(frozen, discard_records=True)
            raise
        finally:
            for hook in self._final_hooks:
                hook.armed = False
        records = [tap.records() for tap in self.taps]
        t_env = np.array([tap.time() for tap in self.taps])
        ended = np.logical_or(terminations, truncations)
        final = np.array([tap.final is not None for tap in self.taps])
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            reset = self._pending.copy()
        else:  # SAME_STEP: a sub-env that ended was reset; its final state was kept
            reset = ended & ~final if self.autoreset_mode == AutoresetMode.SAME_STEP \
                else np.zeros(self.num_envs, bool)
        restart = ~reset & self._clock_faults(t_env)
        self.bank.restarts += int(np.count_nonzero(restart))
        moving = ~reset & ~restart & (t_env > self.bank.t_s)
        if moving.any():
            t, L, V, F, self._source = step_knots(
                self.taps, records, self.bank.t_s, self.bank.length_L0,
                self.bank.velocity_L0_s, moving, self.forces.force_N)
            self.bank.advance(t, L, V, hold=~moving)
            self.forces.advance(F, moving)
            self._measured[moving] = L[-1, moving]
        self._rest(np.flatnonzero(restart))
        if final.any():
            info = self._final_observations(info, np.flatnonzero(final))
        self._rest(np.flatnonzero(reset))
        self._pending = (ended if self.autoreset_mode == AutoresetMode.NEXT_STEP
                         else np.zeros(self.num_envs, bool))
        return self._observation(obs), rewards, terminations, truncations, self._info(info)

    def _clock_faults(self, t_env: np.ndarray) -> np.ndarray:
        """(n,) bool: the sub-envs whose clock ran backwards (it reset itself), is not
        finite, jumped by more than ``max_interval_s``, or moved by another number of
        physics steps than most sub-envs (a clock set by hand in one of them): each is
        restarted at rest at its state rather than carried along."""
        span = t_env - self.bank.t_s
        bad = ~((span >= 0) & (span <= self.taps[0].interval_limit_s))
        steps = np.rint(np.where(bad, 0.0, span) / self.taps[0].timestep_s).astype(np.int64)
        moved = ~bad & (steps > 0)
        if moved.any():
            values, counts = np.unique(steps[moved], return_counts=True)
            common = values[counts == counts.max()]
            # a tie (two sub-envs, one set by hand): the env's own step if it tells it
            usual = common[-1] if self._env_steps not in common else self._env_steps
            bad |= moved & (steps != usual)
        return bad

    def _final_observations(self, info: dict[str, Any], rows: np.ndarray) -> dict[str, Any]:
        """SAME_STEP: ``info["final_obs"]`` / ``["final_info"]`` of the sub-envs ``rows``
        (which ended this step) with the afferents at their final state; then their taps
        read the reset env again."""
        info = dict(info)
        final_obs = info["final_obs"].copy()
        final_info = dict(info.get("final_info", {}))
        for i in rows:
            final_obs[i] = add_afferents(
                final_obs[i], afferent_rates(self.bank, self.forces, self.afferents, int(i)),
                self.observation_mode, self.rate_scale_pps,
                getattr(self.single_observation_space, "dtype", None))
            # batched the way the vector env batches the sub-envs' infos (arrays, _key masks)
            final_info = VectorEnv._add_info(
                self, final_info, {**bank_info(self.bank, self._measured, self._source,
                                               row=int(i)), **self.forces.info(int(i))},
                int(i))
            self.taps[i].thaw()
        info["final_obs"], info["final_info"] = final_obs, final_info
        self._rest(rows, discard_records=True)
        return info

    def close(self, **kwargs: Any) -> None:
        for hook in getattr(self, "_final_hooks", ()):
            hook.remove()
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
            now.append(self.taps[i].state_now())
        t = np.array([self.taps[i].rest_time(x[0]) for i, x in zip(rows, now, strict=True)])
        L = np.stack([x[1] for x in now])
        V = np.stack([x[2] for x in now])
        self.bank.reset(rows, t, L, V)
        self.forces.reset(rows, np.stack([x[3] for x in now]))
        self._measured[rows] = L

    def _observation(self, obs):
        return add_afferents(obs, afferent_rates(self.bank, self.forces, self.afferents),
                             self.observation_mode, self.rate_scale_pps,
                             getattr(self.single_observation_space, "dtype", None))

    def _info(self, info: dict[str, Any]) -> dict[str, Any]:
        out = dict(info)
        signals = {**bank_info(self.bank, self._measured, self._source), **self.forces.info()}
        for key, value in signals.items():
            out[key] = value
            out[f"_{key}"] = np.ones(self.num_envs, dtype=bool)
        out["spindle_substep_source"] = self._source
        out["spindle_substeps_limited"] = self.bank.substeps_limited
        out["spindle_restarts"] = self.bank.restarts
        return out


class FinalStateOnReset:
    """Put on a sub-env as its instance attribute ``reset``: while :attr:`armed` (during the
    vector env's step), it freezes the sub-env's tap (:meth:`EnvTap.freeze`: the state and
    records at the episode's end) before the sub-env's own reset runs. :meth:`remove` takes
    it off."""

    def __init__(self, env: Any, tap: EnvTap) -> None:
        self.env, self.tap, self.armed = env, tap, False
        # an instance attribute reset already there, else None: the class's is called (a
        # bound method kept here would be unpickled as getattr(env, "reset"): this object)
        self.own = env.__dict__.get("reset")
        env.reset = self

    def __call__(self, *args: Any, **kwargs: Any):
        if self.armed:
            self.tap.freeze()
        if self.own is not None:
            return self.own(*args, **kwargs)
        return type(self.env).reset(self.env, *args, **kwargs)

    def remove(self) -> None:
        if self.env.__dict__.get("reset") is self:
            if self.own is not None:
                self.env.reset = self.own
            else:
                del self.env.__dict__["reset"]
