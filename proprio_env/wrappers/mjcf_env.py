"""A plain Gymnasium ``MujocoEnv`` around any MJCF file, and where myo-sim's models are.

``MuscleModelEnv`` is what the tests and ``scripts/bench_wrapper.py`` wrap: a model driven by
its controls, nothing else (no reward, no termination; registered envs add a time limit).
It needs ``gymnasium.envs.mujoco`` (``imageio``) and is imported lazily by the package.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

MYO_SIM_MODELS = {
    "elbow": "legacy/elbow/myoelbow_1dof6muscles.xml",
    "legs_osl": "legacy/osl/myolegs_osl.xml",
}
"""myo-sim's files used here: the 1-DoF 6-muscle elbow, the 54-muscle legs with the Open
Source Leg prosthesis (paths under ``myo_sim.MODELS_DIR``)."""


def myo_sim_model_path(name: str) -> Path:
    """Path of one of :data:`MYO_SIM_MODELS` in the installed ``myo-sim`` package
    (``pip install myo-sim``; ``ImportError`` naming the extra when it is absent)."""
    if name not in MYO_SIM_MODELS:
        raise ValueError(f"name={name!r} is not one of {sorted(MYO_SIM_MODELS)}")
    try:
        import myo_sim
    except ImportError as exc:
        raise ImportError("myo-sim is not installed: pip install --no-deps myo-sim==0.2.4 "
                          "(--no-deps: it declares mujoco<4 but loads in MuJoCo 4, which "
                          "it would otherwise replace), with the 'myo' extra") from exc
    return Path(myo_sim.MODELS_DIR) / MYO_SIM_MODELS[name]


class MuscleModelEnv(MujocoEnv):
    """Any MJCF model as a Gymnasium MuJoCo env, driven by its controls.

    Action: ``ctrl`` of every actuator, within ``actuator_ctrlrange`` (unlimited ones:
    [-1, 1]). Observation: ``qpos`` and ``qvel``. Reward 0; never terminates. Starting
    state: the model's first keyframe if it has one, else ``qpos0``, plus uniform noise of
    ``reset_noise_scale`` on qpos and qvel.

    Args:
        xml_file: the MJCF file.
        frame_skip: physics steps per env step.
        reset_noise_scale: half-width of the reset noise.
        model: a model compiled from ``xml_file`` to copy instead of compiling the file again
            (the envs of a vector env: compiling the 54-muscle legs takes ~0.6 s of CPU and
            touches ~360 MB, most of it system time; a copy takes milliseconds).
    """

    metadata = {"render_modes": ["human", "rgb_array", "depth_array", "rgbd_tuple"]}  # noqa: RUF012

    def __init__(self, xml_file: str | Path, frame_skip: int = 10,
                 reset_noise_scale: float = 0.01, model: mujoco.MjModel | None = None,
                 **kwargs: Any) -> None:
        self.reset_noise_scale = float(reset_noise_scale)
        self._compiled = model
        MujocoEnv.__init__(self, str(Path(xml_file).resolve()), frame_skip,
                           observation_space=None, **kwargs)
        self._compiled = None  # copied into self.model; a pickle of the env would carry it
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.dt)}
        n = self.model.nq + self.model.nv
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64)
        low, high = self.model.actuator_ctrlrange.T.copy()
        unlimited = ~self.model.actuator_ctrllimited.astype(bool)
        low[unlimited], high[unlimited] = -1.0, 1.0
        self.action_space = spaces.Box(low.astype(np.float32), high.astype(np.float32),
                                       dtype=np.float32)

    def _initialize_simulation(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        if self._compiled is None:
            return super()._initialize_simulation()
        model = copy.deepcopy(self._compiled)
        model.vis.global_.offwidth = self.width
        model.vis.global_.offheight = self.height
        return model, mujoco.MjData(model)

    def _set_action_space(self):  # set in __init__ once the model is loaded
        return None

    def step(self, action):
        self.do_simulation(np.asarray(action, dtype=float), self.frame_skip)
        return self._get_obs(), 0.0, False, False, {}

    def reset_model(self):
        noise = self.reset_noise_scale
        qpos = (self.model.key_qpos[0] if self.model.nkey else self.init_qpos).copy()
        qpos = qpos + self.np_random.uniform(-noise, noise, self.model.nq)
        qvel = self.init_qvel + self.np_random.uniform(-noise, noise, self.model.nv)
        self.set_state(qpos, qvel)
        return self._get_obs()

    def _get_obs(self) -> np.ndarray:
        return np.concatenate((self.data.qpos, self.data.qvel))
