"""Native Gymnasium vector envs of the two elbow envs: ``n`` envs stepped together.

``gymnasium.make_vec("proprio_env/ElbowReach-v0", num_envs=n)`` (the ids register this module's
classes as their ``vector_entry_point``) returns an :class:`ElbowReachVectorEnv`; the same for
``ProsthesisElbow-v0``. One vector step advances the physics of every env in one
``mujoco.rollout`` call (:class:`~proprio_env.envs.physics.PhysicsBatch`; ``num_threads=2``
runs it on rollout's pool of two threads), samples every env's sensor (exact lengths, the
angle, or each env's own simulated encoder, :class:`~proprio_env.body.encoder.EncoderBatch`) and
pushes all the arms through one batched spindle chain
(:func:`spindle.chain.make_batched_chain`) in one call.

Conventions (Gymnasium 1.x):

- Sub-env i and a single env are one arithmetic (:class:`~proprio_env.envs.core.EnvCore`
  over n envs, of which the single env is n = 1): ``reset(seed=s)`` seeds sub-env i with
  ``s + i`` (a list of n seeds is accepted too); sub-env i then gives the same observations
  as a single env ``gymnasium.make(id)`` reset with seed ``s + i`` and fed the same actions,
  through autoresets too.
- ``reset`` checks every seed and option of every sub-env before it changes anything: a
  refused reset (ValueError naming the option, the sub-env and the value) leaves every
  sub-env as it was.
- Autoreset mode ``NEXT_STEP`` (``metadata["autoreset_mode"]``): after a step that truncates
  sub-env i, the next ``step`` resets it (its action is ignored) and returns its first
  observation with reward 0 and ``terminated = truncated = False``; the reset draws from the
  sub-env's own generator, as a single env's ``reset()`` without a seed does.
- Truncation after ``max_episode_steps`` steps (200 when made with ``make_vec``), counted by
  the vector env itself; the envs never terminate.
- ``info`` is a dict of arrays: the single env's raw signals, (n,) or (n, 2) each.
- ``render()`` renders the first sub-env; ``close()`` stops the thread pool.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from proprio_env.envs.arguments import check_positive_int, check_reset_options, check_seeds
from proprio_env.envs.core import CoreSettings, Drive, EnvCore
from proprio_env.envs.elbow_reach import MuscleDrive
from proprio_env.envs.physics import PhysicsBatch
from proprio_env.envs.prosthesis_elbow import ServoDrive

__all__ = ["ElbowProprioVectorEnv", "ElbowReachVectorEnv", "ProsthesisElbowVectorEnv"]


class ElbowProprioVectorEnv(CoreSettings, VectorEnv):
    """``num_envs`` elbow envs stepped together (see the module docstring).

    Args:
        num_envs: number of sub-envs (>= 1).
        num_threads: threads stepping the physics (1: the calling thread; 2 uses both cores
            of a 2-core machine).
        max_episode_steps: truncation (``None``: never; ``make_vec`` passes the registered
            200).
        **kwargs: the single env's arguments (``afferent_source``, ``backend``,
            ``control_hz``, ... ; see :class:`~proprio_env.envs.ElbowReachEnv`), checked the
            same way, all before anything is built; ``render_mode="rgb_array"`` renders
            sub-env 0.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 50,
                                          "autoreset_mode": AutoresetMode.NEXT_STEP}
    #: what moves the elbows (set by subclasses)
    drive: ClassVar[type[Drive]] = Drive

    def __init__(self, num_envs: int = 1, *, num_threads: int = 1,
                 max_episode_steps: int | None = None, **kwargs: Any) -> None:
        n = check_positive_int("num_envs", num_envs)
        if max_episode_steps is not None:
            max_episode_steps = check_positive_int("max_episode_steps", max_episode_steps)
        self.core = core = EnvCore(self.drive, n, num_threads, **kwargs)
        self.num_envs = n
        self.max_episode_steps = max_episode_steps
        self.render_mode = core.render_mode
        self.metadata = {**self.metadata, "render_fps": core.control_hz}
        self.single_observation_space = core.observation_space
        self.single_action_space = core.action_space
        self.observation_space = batch_space(core.observation_space, n)
        self.action_space = batch_space(core.action_space, n)
        self.rngs: list[np.random.Generator | None] = [None] * n
        self.episode_steps = np.zeros(n, dtype=np.int64)
        self._autoreset = np.zeros(n, dtype=bool)
        self._ready = False

    @property
    def physics(self) -> PhysicsBatch:
        """Every sub-env's physics (states, controls)."""
        return self.core.physics

    @property
    def num_threads(self) -> int:
        return self.core.physics.num_threads

    @property
    def target_deg(self) -> np.ndarray:
        """Each sub-env's target elbow flexion (deg), (n,)."""
        return self.core.target_deg

    # -- gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None):
        """Reset every sub-env (or those of ``options["reset_mask"]``, a (n,) bool array);
        ``options`` may fix ``"target_deg"`` / ``"angle_deg"`` (a number or one per
        sub-env) as the single env's do. Every seed and option value is checked first (also
        those of sub-envs the mask leaves out); a refusal changes nothing."""
        n = self.num_envs
        seeds = check_seeds(seed, n)
        mask, fixed = check_reset_options(options, self.core.joint_range_deg, n)
        envs = np.arange(n) if mask is None else np.flatnonzero(mask)
        if not self._ready and envs.size < n:
            raise ValueError("the first reset must reset every sub-env (options['reset_mask'] "
                             f"selects {envs.size} of {n})")
        rngs = [self.rngs[i] if seeds[i] is None and self.rngs[i] is not None
                else seeding.np_random(seeds[i])[0] for i in envs.tolist()]
        self.core.reset(envs, rngs, *(None if name not in fixed else fixed[name][envs]
                                      for name in ("target_deg", "angle_deg")))
        for i, rng in zip(envs.tolist(), rngs, strict=True):
            self.rngs[i] = rng
        self.episode_steps[envs] = 0
        self._autoreset[envs] = False
        self._ready = True
        zeros = np.zeros(n)
        return self.core.observations(), self.core.info(np.zeros(n, np.int64), zeros, zeros)

    def step(self, actions):
        """Step every sub-env; the sub-envs that ended at the previous step are reset
        instead (NEXT_STEP autoreset)."""
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        core, n = self.core, self.num_envs
        actions = core.check_actions(actions, (n, *self.single_action_space.shape))
        resetting = self._autoreset
        active = ~resetting if resetting.any() else None
        pushed = core.step(actions, active)
        distance, control = core.rewards(actions)
        self.episode_steps += 1
        if active is not None:
            envs = np.flatnonzero(resetting)
            core.reset(envs, [self.rngs[i] for i in envs.tolist()])
            self.episode_steps[envs] = 0
            distance[envs] = control[envs] = 0.0
            pushed[envs] = 0
        truncated = np.zeros(n, dtype=bool)
        if self.max_episode_steps is not None:
            truncated = self.episode_steps >= self.max_episode_steps
        terminated = np.zeros(n, dtype=bool)
        self._autoreset = terminated | truncated
        return (core.observations(), distance + control, terminated, truncated,
                core.info(pushed, distance, control))

    def render(self):
        """The first sub-env's image (``render_mode="rgb_array"``), else ``None``."""
        return self.core.render(0)

    def close_extras(self, **kwargs: Any) -> None:
        # safe on an object whose constructor refused its arguments: nothing was built
        core = self.__dict__.get("core")
        if core is not None:
            core.close()


class ElbowReachVectorEnv(ElbowProprioVectorEnv):
    """Vector env of :class:`~proprio_env.envs.ElbowReachEnv` (``ElbowReach-v0``)."""

    drive = MuscleDrive


class ProsthesisElbowVectorEnv(ElbowProprioVectorEnv):
    """Vector env of :class:`~proprio_env.envs.ProsthesisElbowEnv` (``ProsthesisElbow-v0``);
    ``info["command_deg"]`` is each servo's command (deg)."""

    drive = ServoDrive
