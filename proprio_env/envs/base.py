"""The single elbow env: one env of the env core (:class:`~proprio_env.envs.core.EnvCore`
with n = 1) behind Gymnasium's ``Env`` API."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import gymnasium as gym
import mujoco
import numpy as np

from proprio_env.envs.arguments import check_reset_options, check_seed
from proprio_env.envs.core import RATE_SCALE_PPS, CoreSettings, Drive, EnvCore

__all__ = ["RATE_SCALE_PPS", "ElbowProprioEnv"]


class ElbowProprioEnv(CoreSettings, gym.Env):
    """Base class; see :class:`~proprio_env.envs.ElbowReachEnv` and
    :class:`~proprio_env.envs.ProsthesisElbowEnv` for the documented envs and their
    keyword arguments."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 50}
    #: what moves the elbow (set by subclasses)
    drive: ClassVar[type[Drive]] = Drive

    def __init__(self, **kwargs: Any) -> None:
        self.core = core = EnvCore(self.drive, 1, **kwargs)
        self.render_mode = core.render_mode
        self.metadata = {**self.metadata, "render_fps": core.control_hz}
        self.observation_space = core.observation_space
        self.action_space = core.action_space
        self._env = np.zeros(1, dtype=np.int64)  # the core's one env
        self._action_shape = core.action_space.shape
        self._ready = False

    # -- gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode. ``options`` may fix ``"target_deg"`` and ``"angle_deg"``
        (elbow flexion, deg, inside the joint range) instead of drawing them. A refused seed
        or option raises ValueError and changes nothing."""
        seed = check_seed("seed", seed)
        _, fixed = check_reset_options(options, self.core.joint_range_deg)
        saved = self._np_random, self._np_random_seed
        super().reset(seed=seed)
        try:
            self.core.reset(self._env, [self.np_random], fixed.get("target_deg"),
                            fixed.get("angle_deg"))
        except BaseException:
            self._np_random, self._np_random_seed = saved
            raise
        self._ready = True
        return self.core.observations()[0], self._info(np.zeros(1, np.int64), 0.0, 0.0)

    def step(self, action):
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        core = self.core
        actions = core.check_actions(action, self._action_shape)[None, :]
        pushed = core.step(actions)
        distance, control = core.rewards(actions, env=0)
        obs = core.observations()[0]
        return obs, distance + control, False, False, self._info(pushed, distance, control)

    def render(self):
        return self.core.render(0)

    def close(self) -> None:
        self.core.close()

    # -- state readouts -----------------------------------------------------------------------
    @property
    def data(self) -> mujoco.MjData:
        """The MuJoCo data the physics steps in: the state after the last step or reset."""
        return self.core.data

    @property
    def angle_deg(self) -> float:
        """Elbow flexion (deg, 0 = straight)."""
        physics = self.core.physics
        return math.degrees(float(physics.state[0, physics.qpos_index]))

    @property
    def target_deg(self) -> float:
        """This episode's target elbow flexion (deg)."""
        return float(self.core.target_deg[0])

    def _info(self, pushed: np.ndarray, distance: float, control: float) -> dict[str, Any]:
        return self.core.info(pushed, distance, control, env=0)
