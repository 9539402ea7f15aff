"""Stable-Baselines3 ``VecEnv`` over a Gymnasium ``VectorEnv`` that autoresets on the next step.

Gymnasium 1.x vector envs (``gym.make_vec``) declare ``metadata["autoreset_mode"]``; ours and
``SyncVectorEnv`` use ``NEXT_STEP``: a sub-env that ends at step t returns its last
observation there and is reset by the *next* ``step`` call, which ignores its action and
returns the reset observation with reward 0. Stable-Baselines3 expects the other convention
(its ``DummyVecEnv``): the step that ends an episode already returns the *reset* observation,
with the last one in ``info["terminal_observation"]`` and ``info["TimeLimit.truncated"]``
telling a time limit from a terminal state (PPO bootstraps the value of truncated episodes
from the terminal observation).

:class:`SB3VectorEnv` converts without stepping anything twice: when sub-envs end, it resets
exactly those through Gymnasium's partial reset (``reset(options={"reset_mask": done})``,
which also clears their pending autoreset), so every ``step`` of the adapter is one ``step``
of the vector env and every other sub-env is untouched. Infos (a dict of arrays with
``_key`` masks) become SB3's list of per-env dicts.

Needs ``stable-baselines3`` (the ``train`` extra).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import (
    VecEnv,
    VecEnvIndices,
    VecEnvObs,
    VecEnvStepReturn,
)

__all__ = ["SB3VectorEnv", "unbatch_info"]


def unbatch_info(info: dict[str, Any], num_envs: int) -> list[dict[str, Any]]:
    """A Gymnasium vector info (arrays over sub-envs, ``"_key"`` masks saying which sub-envs
    hold ``key``; nested dicts likewise) as one dict per sub-env."""
    out: list[dict[str, Any]] = [{} for _ in range(num_envs)]
    for key, value in info.items():
        if key.startswith("_"):
            continue
        mask = info.get(f"_{key}")
        mask = np.ones(num_envs, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        if isinstance(value, dict):
            nested = unbatch_info(value, num_envs)
            for i in np.flatnonzero(mask):
                out[i][key] = nested[i]
        else:
            for i in np.flatnonzero(mask):
                out[i][key] = value[i]
    return out


class SB3VectorEnv(VecEnv):
    """A Gymnasium ``VectorEnv`` (``NEXT_STEP`` autoreset, partial reset via ``reset_mask``)
    as a Stable-Baselines3 ``VecEnv``.

    Args:
        venv: the vector env, e.g. ``gym.make_vec("proprio_env/ElbowReach-v0", num_envs=8)``.
            The adapter owns it (``close`` closes it).

    Seeds: ``seed(s)`` (SB3 seeds sub-env i with ``s + i``) is passed to the next ``reset`` as
    ``reset(seed=s)``, which Gymnasium vector envs expand to ``s, s + 1, ...``. Options must be
    the same for every sub-env (a vector env takes one ``options`` dict). Attributes
    (``get_attr``, ``set_attr``, ``env_method``) are the vector env's, reported once per
    sub-env; ``env_is_wrapped`` is False (sub-envs of a native vector env carry no wrappers).
    """

    def __init__(self, venv: gym.vector.VectorEnv):
        mode = venv.metadata.get("autoreset_mode")
        if mode is not None and AutoresetMode(mode) != AutoresetMode.NEXT_STEP:
            raise ValueError(f"autoreset_mode={mode!r}: SB3VectorEnv needs a vector env that "
                             f"autoresets on the next step ({AutoresetMode.NEXT_STEP!r})")
        self.venv = venv
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space,
                         venv.single_action_space)

    # -- SB3 VecEnv API --------------------------------------------------------------------
    def reset(self) -> VecEnvObs:
        seeds = self._seeds
        if all(s is None for s in seeds):
            seed: int | list[int | None] | None = None
        elif all(s is not None for s in seeds) and list(seeds) == [
                seeds[0] + i for i in range(self.num_envs)]:  # type: ignore[operator]
            seed = seeds[0]
        else:
            seed = list(seeds)
        options = self._options[0]
        if any(o != options for o in self._options):
            raise ValueError(f"per-env reset options {self._options!r}: a vector env takes one "
                             "options dict for all sub-envs")
        obs, info = self.venv.reset(seed=seed, options=dict(options) if options else None)
        self.reset_infos = unbatch_info(info, self.num_envs)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        obs, rewards, terminated, truncated, info = self.venv.step(self._actions)
        self._actions = None
        terminated = np.asarray(terminated, dtype=bool)
        truncated = np.asarray(truncated, dtype=bool)
        dones = terminated | truncated
        infos = unbatch_info(info, self.num_envs)
        obs = np.array(obs, copy=True)
        for i in range(self.num_envs):
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        if dones.any():
            ended = np.flatnonzero(dones)
            for i in ended:
                infos[i]["terminal_observation"] = obs[i].copy()
            reset_obs, reset_info = self.venv.reset(options={"reset_mask": dones.copy()})
            obs[ended] = np.asarray(reset_obs)[ended]
            reset_infos = unbatch_info(reset_info, self.num_envs)
            for i in ended:
                self.reset_infos[i] = reset_infos[i]
        return obs, np.asarray(rewards, dtype=np.float32), dones, infos

    def close(self) -> None:
        self.venv.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        value = getattr(self.venv, attr_name)
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._require_all(indices, "set_attr")
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None,
                   **method_kwargs) -> list[Any]:
        self._require_all(indices, "env_method")
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in range(self.num_envs)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper],
                       indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.venv.render()
        if frames is None:
            return [None]
        if isinstance(frames, np.ndarray) and frames.ndim == 3:
            return [frames]  # a native vector env renders its first sub-env
        return list(frames)

    def _require_all(self, indices: VecEnvIndices, what: str) -> None:
        if sorted(self._get_indices(indices)) != list(range(self.num_envs)):
            raise ValueError(f"{what}(indices={indices!r}): a vector env's attributes are "
                             f"shared by its {self.num_envs} sub-envs; pass indices=None")
