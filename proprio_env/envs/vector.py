"""Native Gymnasium vector envs of the two elbow envs: ``n`` envs stepped together.

``gymnasium.make_vec("proprio_env/ElbowReach-v0", num_envs=n)`` (the ids register this module's
classes as their ``vector_entry_point``) returns an :class:`ElbowReachVectorEnv`; the same for
``ProsthesisElbow-v0``. One vector step advances the physics of every env in one
``mujoco.rollout`` call (:class:`~proprio_env.envs.physics.PhysicsBatch`; ``num_threads=2``
runs it on rollout's pool of two threads), samples every env's sensor (exact lengths, the
angle, or each env's own simulated encoder, :class:`~proprio_env.encoder.EncoderBank`) and
pushes all the arms through one batched spindle chain
(:func:`spindle.chain.make_batched_chain`) in one call.

Conventions (Gymnasium 1.x):

- ``reset(seed=s)`` seeds sub-env i with ``s + i`` (a list of n seeds is accepted too); sub-env
  i then gives the same observations as a single env ``gymnasium.make(id)`` reset with seed
  ``s + i`` and fed the same actions, through autoresets too.
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

from proprio_env.envs.afferents import BatchAfferentReadout
from proprio_env.envs.arguments import check_positive_int
from proprio_env.envs.base import (
    ElbowProprioEnv,
    check_actions,
    check_observations,
    observations,
    rewards,
    step_info,
)
from proprio_env.envs.elbow_reach import ElbowReachEnv
from proprio_env.envs.physics import PhysicsBatch, check_threads
from proprio_env.envs.prosthesis_elbow import ProsthesisElbowEnv

__all__ = ["ElbowProprioVectorEnv", "ElbowReachVectorEnv", "ProsthesisElbowVectorEnv"]


class ElbowProprioVectorEnv(VectorEnv):
    """``num_envs`` copies of a single elbow env stepped together (see the module docstring).

    Args:
        num_envs: number of sub-envs (>= 1).
        num_threads: threads stepping the physics (1: the calling thread; 2 uses both cores
            of a 2-core machine).
        max_episode_steps: truncation (``None``: never; ``make_vec`` passes the registered
            200).
        **kwargs: the single env's arguments (``afferent_source``, ``backend``,
            ``control_hz``, ... ; see :class:`~proprio_env.envs.ElbowReachEnv`), checked the
            same way; ``render_mode="rgb_array"`` renders sub-env 0.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 50,
                                          "autoreset_mode": AutoresetMode.NEXT_STEP}
    single_env_class: ClassVar[type[ElbowProprioEnv]] = ElbowProprioEnv

    def __init__(self, num_envs: int = 1, *, num_threads: int = 1,
                 max_episode_steps: int | None = None, **kwargs: Any) -> None:
        n = check_positive_int("num_envs", num_envs)
        num_threads = check_threads(num_threads)
        if max_episode_steps is not None:
            max_episode_steps = check_positive_int("max_episode_steps", max_episode_steps)
        # One single env holds the checked settings, the model, the spaces and the fits;
        # its MjData serves for resets and rendering.
        self.env = env = self.single_env_class(**kwargs)
        self.num_envs = n
        self.max_episode_steps = max_episode_steps
        self.render_mode = env.render_mode
        self.metadata = {**self.metadata, "render_fps": env.control_hz}
        self.single_observation_space = env.observation_space
        self.single_action_space = env.action_space
        self.observation_space = batch_space(env.observation_space, n)
        self.action_space = batch_space(env.action_space, n)
        self.afferent_source = env.afferent_source
        self.backend = env.backend
        self.num_threads = num_threads
        self.physics = PhysicsBatch(env.model, n, env.frame_skip, num_threads,
                                    qadr=env._qadr, vadr=env._vadr)
        self.afferents = BatchAfferentReadout(n, env.afferent_source,
                                              env.afferents.chain.config,
                                              env.afferents.encoder_params, env.length_fits,
                                              step_s=env.dt)
        self.rngs: list[np.random.Generator | None] = [None] * n
        self.target_deg = np.zeros(n)
        self.episode_steps = np.zeros(n, dtype=np.int64)
        self._autoreset = np.zeros(n, dtype=bool)
        self._sample = None

    # -- gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None):
        """Reset every sub-env (or those of ``options["reset_mask"]``, a (n,) bool array);
        ``options`` may fix ``"target_deg"`` / ``"angle_deg"`` (a scalar or (n,) array) as
        the single env's do."""
        n = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * n
        elif isinstance(seed, int | np.integer) and not isinstance(seed, bool):
            seeds = [int(seed) + i for i in range(n)]
        else:
            seeds = list(seed)
            if len(seeds) != n:
                raise ValueError(f"seed list has length {len(seeds)}, expected num_envs={n}")
        options = {} if options is None else dict(options)
        mask = options.pop("reset_mask", None)
        if mask is None:
            mask = np.ones(n, dtype=bool)
        elif not (isinstance(mask, np.ndarray) and mask.dtype == bool and mask.shape == (n,)
                  and mask.any()):
            raise ValueError(f"options['reset_mask'] must be a bool array of shape ({n},) "
                             "with at least one True")
        fixed = {}
        for key, value in options.items():
            arr = np.broadcast_to(np.asarray(value), (n,)) if key in (
                "target_deg", "angle_deg") else value
            fixed[key] = arr
        envs = np.flatnonzero(mask)
        for i in envs.tolist():
            if seeds[i] is not None or self.rngs[i] is None:
                self.rngs[i], _ = seeding.np_random(seeds[i])
        self._reset_envs(envs, {k: (v[envs] if isinstance(v, np.ndarray) else v)
                                for k, v in fixed.items()})
        self._autoreset[envs] = False
        obs = self._observations()
        zeros = np.zeros(n)
        return obs, self._info(np.zeros(n, dtype=np.int64), zeros, zeros)

    def step(self, actions):
        """Step every sub-env; the sub-envs that ended at the previous step are reset
        instead (NEXT_STEP autoreset)."""
        if self._sample is None:
            raise RuntimeError("call reset() before step()")
        env, n = self.env, self.num_envs
        actions = check_actions(actions, env.action_space, (n, *env.action_space.shape),
                                env.clip_actions, env._action_bounds)
        resetting = self._autoreset.copy()
        active = ~resetting
        physics = self.physics
        env.write_controls(physics.ctrl, actions)
        physics.step()
        angle_deg = np.degrees(physics.angle_rad())
        final = physics.state
        q, v = final[:, physics.qpos_index], final[:, physics.qvel_index]
        bad = active & ~(np.isfinite(q) & np.isfinite(v))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise RuntimeError(f"physics diverged in env {i}: elbow angle {q[i]!r} rad, "
                               f"velocity {v[i]!r} rad/s")
        lengths = None
        if self.afferent_source == "exact":
            mtu = physics.tendon_lengths_m(env.data)
            lengths = env._fibre_lengths(mtu.reshape(-1, 2)).reshape(mtu.shape)
        self._sample, pushed = self.afferents.push(physics.time_s(), angle_deg, lengths,
                                                   active)
        reward, distance, control = rewards(angle_deg[:, -1], self.target_deg, actions,
                                            env.distance_reward_weight,
                                            env.control_cost_weight)
        self.episode_steps += 1
        if resetting.any():
            envs = np.flatnonzero(resetting)
            self._reset_envs(envs, {})
            reward[envs] = distance[envs] = control[envs] = 0.0
            pushed[envs] = 0
        truncated = np.zeros(n, dtype=bool)
        if self.max_episode_steps is not None:
            truncated = self.episode_steps >= self.max_episode_steps
        terminated = np.zeros(n, dtype=bool)
        self._autoreset = terminated | truncated
        obs = self._observations()
        return obs, reward, terminated, truncated, self._info(pushed, distance, control)

    def render(self):
        """The first sub-env's image (``render_mode="rgb_array"``), else ``None``."""
        if self.render_mode != "rgb_array":
            return None
        self.physics.load(0, self.env.data)
        self.env._target_deg = float(self.target_deg[0])
        return self.env.render()

    def close_extras(self, **kwargs: Any) -> None:
        self.physics.close()
        self.env.close()

    # -- helpers ------------------------------------------------------------------------------
    def _reset_envs(self, envs: np.ndarray, options: dict[str, Any]) -> None:
        """Reset the sub-envs ``envs`` (their generators continue), as a single env's
        ``reset`` does: target, initial angle, physics at rest, chain, encoder."""
        env, physics = self.env, self.physics
        m = envs.size
        angles, lengths, times = np.empty(m), np.empty((m, 2)), np.empty(m)
        rngs = []
        for j, i in enumerate(envs.tolist()):
            opts = {k: float(v[j]) if isinstance(v, np.ndarray) else v
                    for k, v in options.items()}
            rng = self.rngs[i]
            target, angle = env.draw_start(rng, opts)
            self.target_deg[i] = target
            angles[j] = angle
            lengths[j] = env.reset_physics(env.data, angle)
            times[j] = env.data.time
            physics.store(i, env.data)
            rngs.append(rng)
        self.afferents.reset(envs, times, angles, lengths, rngs)
        self._sample = self.afferents.chain.last
        self.episode_steps[envs] = 0

    def _observations(self) -> np.ndarray:
        s = self._sample = self.afferents.chain.last
        obs = observations(s.ia_pps, s.ii_pps, s.gamma_static_pps, s.gamma_dynamic_pps,
                           np.radians(self.target_deg), self.env.include_fusimotor)
        check_observations(obs, s.t_s)
        return obs

    def _info(self, pushed: np.ndarray, distance: np.ndarray, control: np.ndarray
              ) -> dict[str, Any]:
        state, physics = self.physics.state, self.physics
        angle = np.degrees(state[:, physics.qpos_index])
        info = step_info(self._sample, state[:, 0].copy(), angle,
                         np.degrees(state[:, physics.qvel_index]), self.target_deg.copy(),
                         pushed, distance, control)
        return info


class ElbowReachVectorEnv(ElbowProprioVectorEnv):
    """Vector env of :class:`~proprio_env.envs.ElbowReachEnv` (``ElbowReach-v0``)."""

    single_env_class = ElbowReachEnv


class ProsthesisElbowVectorEnv(ElbowProprioVectorEnv):
    """Vector env of :class:`~proprio_env.envs.ProsthesisElbowEnv` (``ProsthesisElbow-v0``);
    ``info["command_deg"]`` is each servo's command (deg)."""

    single_env_class = ProsthesisElbowEnv

    def _info(self, pushed, distance, control):
        info = super()._info(pushed, distance, control)
        info["command_deg"] = np.degrees(self.physics.ctrl[:, self.env._servo_id])
        return info
